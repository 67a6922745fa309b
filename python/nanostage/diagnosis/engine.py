"""The diagnosis engine: calibrate the nominal model, fit every candidate effect on the
training experiments, judge it on the validation experiments, select effects forward, and
assemble the report.

The gap
    For each sample, measured feedback reading minus the simulated mean reading
    ``x_sim − q/2`` (``q`` the encoder count: a floor quantiser reads on average half a count
    low). Using the mean reading keeps the fit objective smooth in the parameters; its floor
    for a perfect model is the quantisation noise ``q/√12`` plus sensor noise plus the
    trial-to-trial friction scatter. Experiments are weighted equally (each contributes its
    mean square).

Significance (documented in docs/diagnosis.md)
    A candidate is *significant* when all hold: (1) its validation mean-square gap is lower
    than the nominal model's by more than the noise floor allows: the bootstrap over
    validation experiments (resampled with replacement) gives a reduction ≤ 0 in fewer than
    5 % of resamples; (2) the RMS shrink exceeds a complexity penalty of
    ``0.03 + 0.02·(number of parameters)``; (3) the reduction of the mean square exceeds
    ``1.5 ×`` the floor's mean square divided by the number of validation experiments (what
    refitting to noise can buy).
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import sys
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.optimize import least_squares
from scipy.stats import qmc

from ..config import System
from ..experiment import Experiment
from ..simulate import simulate_batch
from .candidates import Candidate, Param, applicable_candidates

__all__ = [
    "CandidateResult",
    "DiagnosisSettings",
    "Fit",
    "FitProblem",
    "SimulationCache",
    "crossfit_folds",
    "crossfit_models",
    "diagnose_experiments",
    "experiment_floors_m",
    "experiment_kind",
    "indistinguishable",
    "log_occam_factor",
    "noise_floor_m",
    "pick_winner",
    "with_starts",
]

FloatArray = npt.NDArray[np.float64]
#: The gap charged for a parameter set whose model is invalid or whose simulation fails, m.
FAILED_GAP_M = 1e-3
#: Turns the model into the system of one experiment (its controller gains).
Adapt = Callable[[System, Experiment], System]


@dataclass(frozen=True, slots=True, kw_only=True)
class DiagnosisSettings:
    """Knobs of the engine (defaults suit ~10 experiments in about a minute on 2 cores)."""

    n_starts_nominal: int = 3
    n_starts_candidate: int = 3
    #: Starts of a friction-model candidate's refit in the first round (`lugre`, `gms`, …;
    #: screening as :attr:`screen_starts_friction_models`; later rounds
    #: :attr:`n_starts_candidate`: on the speed bench's backlash case six starts on top of
    #: the hunting backlash took the diagnosis from 46 to 72 s). A friction model replaces
    #: the table friction, so its warm start is not the model before, and its gap has many
    #: basins: on the 12 presliding cases of benchmark seeds 22 and 23, the GMS candidate
    #: fitted alone from 6 starts instead of 3 ended at a smaller training gap in 6 (by
    #: 21–58 %), and its validation shrink rose in 5 of them (median of the 12 from 0.41
    #: to 0.56).
    n_starts_friction_models: int = 6
    max_nfev_per_param: int = 12
    diff_step: float = 0.03
    bootstrap: int = 400
    p_value: float = 0.05
    penalty_base: float = 0.03
    penalty_per_param: float = 0.02
    floor_factor: float = 1.5
    #: A candidate is significant only if the validation gap before exceeds this many
    #: noise floors (0 turns the rule off). Measured in stop 14 on seeds 12 and 13: off, it
    #: found three more dwell cases and made two false alarms in twelve no-effect cases.
    explainable_factor: float = 1.5
    #: Judge candidates with each validation experiment weighted by the inverse square of
    #: its own noise floor (:func:`experiment_floors_m`) instead of one floor for all.
    kind_floors: bool = True
    command_tolerance: float = 1.1
    forward_rounds: int = 3
    forward_top: int = 8
    refine_top: int = 4
    #: Also refine the best-screened friction-model candidate outside the best
    #: :attr:`refine_top`: a friction model replaces the table friction, so its screening
    #: starts are not near the model before, and its screened gap says less about its best
    #: fit than another candidate's (on a presliding case of seed 19 LuGre was among the
    #: best four, the GMS candidate screened sixth, 108 nm, and refitted alone at 47 nm).
    refine_best_friction_model: bool = True
    #: Break a tie by the Occam factor (:func:`log_occam_factor`): among the significant
    #: candidates the validation data cannot tell from the best (:func:`indistinguishable`),
    #: select the one whose own parameters the data pin down most within their bounds (the
    #: Laplace approximation of the Bayesian evidence with uniform priors on the bounds; the
    #: likelihoods count as equal in a tie). Off: the smallest validation gap, a difference
    #: within the noise. Measured on the stored reports of seven benchmark seeds (first
    #: selections, offline, in-sample): 19 picks turned right, 4 wrong; on two seeds drawn
    #: afterwards (22, 23) top-1 97.6 % and 95.2 % against 90.5 % and 88.1 % without it.
    occam_tie_break: bool = True
    #: Significant candidates of a round whose free values restart the model before
    #: (refitting alone), the best first; None: every significant one, ≤ 0: none. With the
    #: best two only (the default until stop 21), a third significant candidate could be
    #: selected by the tie-break without its control: on the speed bench's delay case,
    #: refitted friction models ranked ahead of the drive compliance whose free values had
    #: restarted the delay model from 511 to 401 nm, and the compliance was selected as a
    #: second effect.
    refit_control_top: int | None = None
    #: Points of the coarse scan over a candidate's own parameters before its local fits,
    #: per parameter of the candidate (at most :attr:`scan_points_max`). The closed loop's
    #: gap is rugged where stick-slip makes the response chaotic: on a dwell case the good
    #: region of (rise, time constant) covered a few per cent of the box.
    scan_points: int = 16
    scan_points_max: int = 48
    #: Local fits when screening a friction-model candidate (`lugre`, `gms`, …): from the
    #: warm start and from the scan's best point (others: the better of the two only).
    screen_starts_friction_models: int = 2
    #: Points of the coarse scan over the free parameters before the first calibration.
    scan_points_nominal: int = 24
    #: Start values of candidates' own parameters, by candidate name and parameter name
    #: (replacing each :class:`Param`'s ``initial``): prior knowledge of an effect, or the
    #: benchmark's truth-started check (is the hidden effect detectable at all?).
    candidate_starts: Mapping[str, Mapping[str, float]] | None = None
    seed: int = 0
    #: Threads of each batch of simulations (0: one per CPU).
    workers: int = 0
    #: Folds of the final cross-fit over the validation experiments (report ``crossfit``;
    #: 0 turns it off): each validation experiment judged by the nominal and the selected
    #: model refitted on all the other experiments.
    crossfit_folds: int = 3
    #: Candidates fitted at once within a round (Python threads; each fit's simulations
    #: still run as batches on ``workers`` threads). The results do not depend on it.
    parallel_candidates: int = 2
    #: Memory for simulations kept for reuse within one diagnosis (:class:`SimulationCache`),
    #: MB; 0 turns the reuse off. The results do not depend on it: a candidate's refit
    #: repeats its screening's scan and local fits exactly, and these are looked up instead
    #: of simulated again.
    simulation_cache_mb: float = 512.0


def with_starts(
    cands: Sequence[Candidate], starts: Mapping[str, Mapping[str, float]] | None
) -> list[Candidate]:
    """``cands`` with the start values ``starts[name][param]`` as their parameters' initial
    values (clipped to the bounds). An unknown parameter name raises ``ValueError``."""
    if not starts:
        return list(cands)
    out = []
    for c in cands:
        given = starts.get(c.name, {})
        names = [p.name for p in c.params]
        unknown = sorted(set(given) - set(names))
        if unknown:
            raise ValueError(
                f"candidate_starts[{c.name!r}]: unknown parameter(s) {', '.join(unknown)}; "
                f"valid: {', '.join(names) or 'none (a discrete candidate)'}"
            )
        params = tuple(
            dataclasses.replace(p, initial=min(max(float(given[p.name]), p.lower), p.upper))
            if p.name in given
            else p
            for p in c.params
        )
        out.append(dataclasses.replace(c, params=params))
    return out


def _progress(msg: str, enabled: bool) -> None:
    if enabled:
        print(msg, file=sys.stderr, flush=True)


@dataclass(frozen=True, slots=True, kw_only=True)
class Fit:
    """A fitted model: its parameter values (dotted paths of free nominal parameters and
    ``effect.param`` names), standard errors, training RMS gap and the system."""

    values: dict[str, float]
    std_errors: dict[str, float]
    train_rms_m: float
    n_evaluations: int
    system: System = field(repr=False)
    #: Covariance of the fitted parameters (in the order of ``values``) in normalised
    #: coordinates, where each parameter's bounds span 1 (log space for a log parameter);
    #: the standard errors are its diagonal in physical units. A direction the data do not
    #: constrain has variance 0 (a pseudo-inverse), not ∞.
    unit_covariance: FloatArray = field(
        default_factory=lambda: np.zeros((0, 0)), repr=False, compare=False
    )


class FitProblem:
    """Least-squares fit of some parameters of a system to experiments, simulation in the
    loop. ``build(values)`` turns physical parameter values into a system."""

    def __init__(
        self,
        params: Sequence[tuple[str, Param]],
        build: Callable[[Sequence[float]], System],
        experiments: Sequence[Experiment],
        threads: int,
        adapt: Adapt,
        cache: SimulationCache | None = None,
    ) -> None:
        self.params = list(params)
        self.build = build
        self.experiments = list(experiments)
        #: Simulation threads of each batch (0: one per CPU).
        self.threads = threads
        self.adapt = adapt
        #: Simulations seen before (shared by the problems of one diagnosis), or None.
        self.cache = cache
        self.n_evaluations = 0
        self.scale_m = 1e-7
        #: :func:`gap_plan` of each experiment (by name), computed on first use.
        self._plans: dict[str, list[HoldPlan]] = {}

    def residuals(self, system: System, experiments: Sequence[Experiment]) -> list[FloatArray]:
        """Per-experiment gap (measured − simulated mean reading)."""
        return self.residuals_of([system], experiments)[0]

    def residuals_and_commands(
        self, system: System, experiments: Sequence[Experiment]
    ) -> tuple[list[FloatArray], list[float | None]]:
        """:meth:`residuals`, and each experiment's mean-square command residual (V², None
        where the experiment has no measured command)."""
        return self._simulate([system], experiments)[0]

    def residuals_of(
        self, systems: Sequence[System], experiments: Sequence[Experiment]
    ) -> list[list[FloatArray]]:
        """:meth:`residuals` of several systems, all their simulations in one batch of the
        core."""
        return [gaps for gaps, _ in self._simulate(systems, experiments)]

    def _simulate(
        self, systems: Sequence[System], experiments: Sequence[Experiment]
    ) -> list[tuple[list[FloatArray], list[float | None]]]:
        n = len(experiments)
        pairs = [(self.adapt(s, e), e) for s in systems for e in experiments]
        simulate = simulate_readings_and_commands if self.cache is None else self.cache.simulate
        sims = simulate([a for a, _ in pairs], [e for _, e in pairs], self.threads)
        out = []
        for j in range(len(systems)):
            gaps: list[FloatArray] = []
            command: list[float | None] = []
            for e, (reading, cmd) in zip(experiments, sims[j * n : (j + 1) * n], strict=True):
                if e.name not in self._plans:
                    self._plans[e.name] = gap_plan(e.position_m, e.reference_m)
                gaps.append(apply_gap_plan(self._plans[e.name], e.position_m, reading))
                command.append(
                    None if e.command_v is None else float(np.mean((e.command_v - cmd) ** 2))
                )
            out.append((gaps, command))
        return out

    def _failed_vector(self) -> FloatArray:
        # A failed simulation (or an invalid combination, e.g. a Coulomb level above the
        # static one) is a very bad fit, not a crash: a gap of 1 mm in every sample, far
        # worse than any valid model (the residuals are in counts).
        return np.concatenate(
            [
                np.full(len(e.time_s), FAILED_GAP_M / (self.scale_m * math.sqrt(len(e.time_s))))
                for e in self.experiments
            ]
        )

    def _scaled(self, res: Sequence[FloatArray]) -> FloatArray:
        # In counts (well-scaled for the optimiser's tolerances), each experiment weighted by
        # 1/√n so that it contributes its mean square.
        return np.concatenate([r / (self.scale_m * math.sqrt(len(r))) for r in res])

    def _vector(self, u: FloatArray) -> FloatArray:
        return self._vectors([u])[0]

    def _vectors(self, us: Sequence[FloatArray]) -> list[FloatArray]:
        """The scaled residual vector at each normalised point of ``us``, every valid
        point's simulations in one batch. Equal, point by point, to evaluating the points
        one at a time (each simulation depends only on its own system and experiment)."""
        self.n_evaluations += len(us)
        systems: list[System | None] = []
        for u in us:
            values = [p.from_unit(float(x) - 1.0) for (_, p), x in zip(self.params, u, strict=True)]
            try:
                systems.append(self.build(values))
            except ValueError:
                systems.append(None)
        it = iter(self.residuals_or_none([s for s in systems if s is not None]))
        out = []
        for maybe in systems:
            r = None if maybe is None else next(it)
            out.append(self._failed_vector() if r is None else self._scaled(r))
        return out

    def residuals_or_none(self, systems: Sequence[System]) -> list[list[FloatArray] | None]:
        """:meth:`residuals_of` on the problem's experiments, None for a system whose
        simulation fails. One failed run fails its whole batch: the batch is then run again
        one system at a time to tell which."""
        try:
            return list(self.residuals_of(systems, self.experiments))
        except (RuntimeError, ValueError):
            if len(systems) == 1:
                return [None]
            return [self.residuals_or_none([s])[0] for s in systems]

    def _batch_map(
        self, fun: Callable[[FloatArray], FloatArray], points: Iterable[FloatArray]
    ) -> list[FloatArray]:
        """The map-like ``workers`` of :func:`scipy.optimize.least_squares`: its
        finite-difference points (one per parameter) evaluated as one batch. ``fun`` is
        scipy's wrapper of :meth:`_vector`, which this evaluates directly."""
        del fun
        return self._vectors(list(points))

    def fit(
        self,
        n_starts: int,
        settings: DiagnosisSettings,
        seed: int,
        n_warm: int = 0,
        prior: Sequence[float] | None = None,
        scan: int = 0,
        scan_starts: int = 1,
    ) -> Fit:
        """Bounded multi-start least squares (scipy ``trf``) in normalised coordinates. The
        first start is every parameter's ``initial``; with ``prior`` (physical values, e.g.
        the preset's values of warm-started parameters) the second start is ``prior``; the
        others draw the parameters after the first ``n_warm`` (which keep their initial,
        warm values) by Latin hypercube. With ``scan`` > 0, the gap is first evaluated at
        ``scan`` Latin-hypercube points of the drawn parameters (all of them without warm
        ones), and the
        best of them (if better than the warm start) is fitted first: instead of the warm
        start when only one start is allowed, else right after it. ``scan_starts`` > 1 adds
        the next best scanned points (better than the warm start) as further starts."""
        k = len(self.params)
        self.scale_m = self.build([p.initial for _, p in self.params]).encoder.count_m
        if k == 0:
            system = self.build([])
            res = self.residuals(system, self.experiments)
            return Fit(
                values={},
                std_errors={},
                train_rms_m=_rms(res),
                n_evaluations=1,
                system=system,
            )
        first = np.array([1.0 + p.to_unit(p.initial) for _, p in self.params])
        starts = [first]
        if prior is not None:
            second = np.array(
                [1.0 + p.to_unit(v) for (_, p), v in zip(self.params, prior, strict=True)]
            )
            if not np.allclose(second, first):
                starts.append(second)
        n_draw = k - n_warm if k > n_warm else k
        if scan > 0 and n_draw > 0:
            # A coarse global look at the drawn (effect) parameters before the local fits:
            # the closed loop's gap is rugged, and a start far from the right basin can end
            # in a poor local optimum. The best scanned point replaces the warm start when
            # it is better, else it becomes the next start.
            rows = qmc.LatinHypercube(d=n_draw, seed=seed + 7919).random(scan)
            cands = []
            for row in rows:
                u = first.copy()
                u[k - n_draw :] = 1.0 + row
                cands.append(u)
            costs = [float(np.sum(v**2)) for v in self._vectors([first, *cands])]
            # The best `scan_starts` scanned points that beat the warm start, best first.
            best_scanned = [
                cands[i - 1]
                for i in np.argsort(costs, kind="stable")
                if i > 0 and costs[i] < costs[0]
            ][: max(scan_starts, 1)]
            if best_scanned:
                if n_starts <= 1:
                    starts[0:1] = best_scanned  # instead of the warm start
                else:
                    starts[1:1] = best_scanned  # right after it
                n_starts += len(best_scanned) - 1
        if n_starts > len(starts):
            lhs = qmc.LatinHypercube(d=n_draw, seed=seed).random(n_starts - len(starts))
            for row in lhs:
                u = first.copy()
                u[k - n_draw :] = 1.0 + row
                starts.append(u)
        starts = starts[: max(n_starts, 1)] if scan > 0 else starts
        best: Any = None
        for u0 in starts:
            sol = least_squares(
                self._vector,
                np.clip(u0, 1.0, 2.0),
                bounds=(1.0, 2.0),
                method="trf",
                diff_step=settings.diff_step,
                max_nfev=settings.max_nfev_per_param * (k + 1),
                x_scale=1.0,
                xtol=1e-4,
                ftol=1e-4,
                gtol=1e-6,
                workers=self._batch_map,
            )
            if best is None or sol.cost < best.cost:
                best = sol
        values = [
            p.from_unit(float(x) - 1.0) for (_, p), x in zip(self.params, best.x, strict=True)
        ]
        std, cov = _uncertainty(best, self.params)
        try:
            system = self.build(values)
        except ValueError as exc:
            raise ValueError(
                f"no valid model within the bounds of {[n for n, _ in self.params]}: {exc}"
            ) from exc
        return Fit(
            values={n: v for (n, _), v in zip(self.params, values, strict=True)},
            std_errors={n: s for (n, _), s in zip(self.params, std, strict=True)},
            train_rms_m=self.scale_m * math.sqrt(2.0 * best.cost / len(self.experiments)),
            n_evaluations=self.n_evaluations,
            system=system,
            unit_covariance=cov,
        )


def _uncertainty(sol: Any, params: Sequence[tuple[str, Param]]) -> tuple[list[float], FloatArray]:
    """Standard errors in physical units, and the covariance in the fit's normalised
    coordinates, from the Jacobian at the optimum (residual samples are autocorrelated: the
    variance is inflated by the residual's integrated autocorrelation time)."""
    jac = np.asarray(sol.jac, dtype=np.float64)
    n, k = jac.shape
    dof = max(n - k, 1)
    # Residual samples are autocorrelated: inflate the variance by the integrated
    # autocorrelation time (in samples) of the residual.
    s2 = 2.0 * float(sol.cost) / dof * autocorrelation_time(np.asarray(sol.fun))
    try:
        cov = np.linalg.pinv(jac.T @ jac) * s2
    except np.linalg.LinAlgError:
        return [math.inf] * k, np.zeros((0, 0))
    cov = 0.5 * (cov + cov.T)  # exactly symmetric (the pseudo-inverse is to rounding)
    out = []
    for i, (_, p) in enumerate(params):
        u = float(sol.x[i]) - 1.0
        eps = 1e-6
        dv = (p.from_unit(min(u + eps, 1.0)) - p.from_unit(max(u - eps, 0.0))) / (
            min(u + eps, 1.0) - max(u - eps, 0.0)
        )
        var = float(cov[i, i])
        out.append(abs(dv) * math.sqrt(var) if var > 0 and math.isfinite(var) else math.inf)
    return out, np.asarray(cov, dtype=np.float64)


def hold_intervals(reference_m: npt.ArrayLike, min_samples: int = 20) -> list[tuple[int, int]]:
    """(start, stop) of each stretch of at least ``min_samples`` where the reference is
    constant (after a step, or a rest between ramps)."""
    ref = np.asarray(reference_m, dtype=np.float64)
    const = np.r_[False, np.diff(ref) == 0]
    out = []
    k, n = 0, len(ref)
    while k < n:
        if const[k]:
            a = k - 1 if k > 0 else 0
            while k < n and const[k]:
                k += 1
            if k - a >= min_samples:
                out.append((a, k))
        else:
            k += 1
    return out


#: A hold is *unsettled* at its end when the measured position still spans more than this
#: many quanta (the smallest changes between samples: an encoder count) over its last
#: :data:`SETTLE_WINDOW` samples, and more than :data:`UNSETTLED_STEP_FRACTION` of the step
#: into it.
UNSETTLED_QUANTA = 4.0
UNSETTLED_STEP_FRACTION = 0.02
SETTLE_WINDOW = 50


def move_units(reference_m: npt.ArrayLike) -> list[tuple[int, int]]:
    """The experiment cut into its moves, (start, stop) each: a new unit starts where the
    reference settles at a new value (each hold after the first); the rest before the first
    move belongs to the first unit. A reference without holds is one unit."""
    ref = np.asarray(reference_m, dtype=np.float64)
    starts = [a for a, _ in hold_intervals(ref) if a > 0]
    bounds = [0, *starts[1:], len(ref)] if starts else [0, len(ref)]
    return list(itertools.pairwise(bounds))


def _quantum(m: FloatArray) -> float:
    d = np.abs(np.diff(m))
    d = d[d > 0]
    # The 5th percentile of the nonzero changes: one count for encoder data however fast
    # the axis moves, the noise level for a continuous sensor.
    return float(np.percentile(d, 5.0)) if d.size else 0.0


def gap_residual(
    measured_m: npt.ArrayLike, simulated_m: npt.ArrayLike, reference_m: npt.ArrayLike
) -> FloatArray:
    """The gap of one experiment: measured − simulated, sample by sample, except where the
    reference is constant from the moment the measured position first reaches it (or from
    the second half of that stretch, if it never does): there the *sorted* values are
    compared — the distribution of positions (mean, overshoot amplitude, limit-cycle
    amplitude) but not the phase of an oscillation, which no model reproduces sample by
    sample once it is chaotic (backlash hunting, stick-slip).

    A move that starts while the measured position is still hunting (the previous hold is
    unsettled at its end, see :data:`UNSETTLED_QUANTA`) starts from the phase of that
    oscillation, which no model reproduces either: its transient is compared after the time
    shift of at most :data:`SETTLE_WINDOW` samples that fits best (the minimum over shifts
    is still a continuous function of the model). Which samples are compared how depends on
    the measured data only.

    An experiment whose reference never moves is driven by a known input (an open-loop
    pulse or a disturbance test): its response is compared sample by sample throughout."""
    return apply_gap_plan(gap_plan(measured_m, reference_m), measured_m, simulated_m)


#: How :func:`gap_residual` compares one hold: ``(a, h, b, aligned, order)``: samples
#: ``[a, h)`` sample by sample (after the best time shift when ``aligned``), ``[h, b)`` as
#: sorted values (``order``: the measured samples' ranks there).
HoldPlan = tuple[int, int, int, bool, npt.NDArray[np.intp]]


def gap_plan(measured_m: npt.ArrayLike, reference_m: npt.ArrayLike) -> list[HoldPlan]:
    """The part of :func:`gap_residual` that depends on the measured data only (computed
    once per experiment by the fits, which compare many simulations with it)."""
    m = np.asarray(measured_m, dtype=np.float64)
    ref = np.asarray(reference_m, dtype=np.float64)
    if ref.size == 0 or np.all(ref == ref[0]):
        return []
    q = _quantum(m)
    plan: list[HoldPlan] = []
    unsettled = False
    for a, b in hold_intervals(ref):
        step = abs(ref[a] - ref[a - 1]) if a > 0 else 0.0
        side = np.sign(m[a:b] - ref[a])
        start_side = side[0]
        crossed = np.flatnonzero(side != start_side) if start_side != 0 else np.array([0])
        h = a + int(crossed[0]) if crossed.size else a + (b - a) // 2
        plan.append((a, h, b, unsettled and h > a, np.argsort(m[h:b], kind="stable")))
        tail = m[max(a, b - SETTLE_WINDOW) : b]
        spread = float(np.ptp(tail)) if tail.size else 0.0
        unsettled = spread > UNSETTLED_QUANTA * q and spread > UNSETTLED_STEP_FRACTION * step
    return plan


def apply_gap_plan(
    plan: Sequence[HoldPlan], measured_m: npt.ArrayLike, simulated_m: npt.ArrayLike
) -> FloatArray:
    """:func:`gap_residual` from its plan (:func:`gap_plan` of the same measured data)."""
    m = np.asarray(measured_m, dtype=np.float64)
    s = np.asarray(simulated_m, dtype=np.float64)
    r = m - s
    for a, h, b, aligned_move, order in plan:
        if aligned_move:
            r[a:h] = m[a:h] - _best_shift(m, s, a, h, SETTLE_WINDOW)
        if b - h > 1:
            aligned = np.empty(b - h)
            aligned[order] = np.sort(s[h:b])
            r[h:b] = m[h:b] - aligned
    return r


def _best_shift(m: FloatArray, s: FloatArray, a: int, h: int, window: int) -> FloatArray:
    """``s`` over ``[a, h)`` delayed or advanced by the whole number of samples (at most
    ``window``) that matches ``m`` there best (indices clamped to the record). Ties go to no
    shift, then to the most negative shift."""
    shifts = np.arange(-window, window + 1)
    idx = np.clip(np.arange(a, h)[None, :] + shifts[:, None], 0, len(s) - 1)
    cands = s[idx]
    costs = np.sum((m[a:h][None, :] - cands) ** 2, axis=1)
    k = window if costs[window] <= costs.min() else int(np.argmin(costs))
    best: FloatArray = cands[k]
    return best


def align_holds(
    measured_m: npt.ArrayLike, simulated_m: npt.ArrayLike, reference_m: npt.ArrayLike
) -> FloatArray:
    """The simulated signal with the samples of each hold window re-ordered to rank-match
    the measured ones, so that ``measured − aligned`` is :func:`gap_residual`."""
    out: FloatArray = np.asarray(measured_m, dtype=np.float64) - gap_residual(
        measured_m, simulated_m, reference_m
    )
    return out


def autocorrelation_time(r: FloatArray, max_lag: int = 500) -> float:
    """Integrated autocorrelation time ``1 + 2·Σρ(k)``, summed until ρ first drops below 0."""
    r = r - float(np.mean(r))
    var = float(np.dot(r, r))
    if var <= 0.0 or len(r) < 4:
        return 1.0
    tau = 1.0
    for lag in range(1, min(max_lag, len(r) // 2)):
        rho = float(np.dot(r[:-lag], r[lag:])) / var
        if rho <= 0.0:
            break
        tau += 2.0 * rho
    return tau


def _rms(res: Sequence[FloatArray]) -> float:
    return math.sqrt(float(np.mean([np.mean(r**2) for r in res])))


def simulate_reading_and_command(system: System, exp: Experiment) -> tuple[FloatArray, FloatArray]:
    """The simulated mean reading (true position of the sensor's side minus half a count)
    and the controller's output in volts, on the experiment's samples."""
    return simulate_readings_and_commands([system], [exp])[0]


def simulate_readings_and_commands(
    systems: Sequence[System], experiments: Sequence[Experiment], threads: int = 0
) -> list[tuple[FloatArray, FloatArray]]:
    """:func:`simulate_reading_and_command` for each (system, experiment) pair, simulated in
    one parallel batch of the core (``threads`` workers; 0: one per CPU)."""
    for system, exp in zip(systems, experiments, strict=True):
        t = system.sample_period_s
        if abs(exp.sample_period_s - t) > 1e-3 * t:
            raise ValueError(
                f"experiment {exp.name!r} ({exp.source}): sample period "
                f"{exp.sample_period_s:g} s differs from the controller's {t:g} s"
            )
    traces = simulate_batch(
        systems,
        [e.reference_m for e in experiments],
        force_disturbances_n=[e.disturbance_n for e in experiments],
        command_disturbances_v=[e.disturbance_v for e in experiments],
        initial_positions_m=[
            float(e.position_m[0]) + 0.5 * s.encoder.count_m
            for s, e in zip(systems, experiments, strict=True)
        ],
        threads=threads,
    )
    out = []
    for system, tr in zip(systems, traces, strict=True):
        q = system.encoder.count_m
        x = tr.motor_position_m if system.encoder.side == "motor" else tr.position_m
        reading: FloatArray = x - 0.5 * q
        command: FloatArray = tr.command * tr.output_unit_v
        out.append((reading, command))
    return out


class SimulationCache:
    """The simulated reading and command (:func:`simulate_readings_and_commands`) of each
    (system, experiment) pair simulated so far, the least recently used dropped beyond
    ``max_bytes``. A simulation is a deterministic function of its system and experiment (the
    same trace bit for bit whatever the batch or thread count), so a pair seen before is
    looked up instead of simulated: the results are those without the cache. Within a
    diagnosis a candidate's refit repeats its screening's scan and local fits from the same
    starts, and a discrete candidate's fits repeat its setting's start.

    Systems are compared by value (``System`` is a frozen dataclass), experiments by
    identity; an entry keeps its experiment alive. By value means ``0.0 == -0.0``: two
    systems differing only in the sign of a zero share an entry (their simulations could
    differ in the last bit where that sign reaches the arithmetic). Thread-safe
    (candidates are fitted on several Python threads); a batch's misses are simulated as one
    batch, outside the lock. The stored arrays are read-only."""

    def __init__(self, max_bytes: float) -> None:
        if not max_bytes >= 0.0:
            raise ValueError(f"SimulationCache max_bytes = {max_bytes!r}: must be ≥ 0")
        self.max_bytes = max_bytes
        self.n_bytes = 0
        self.hits = 0
        self.misses = 0
        self._lock = threading.Lock()
        self._entries: OrderedDict[
            tuple[System, int], tuple[Experiment, FloatArray, FloatArray]
        ] = OrderedDict()

    def __len__(self) -> int:
        return len(self._entries)

    def simulate(
        self, systems: Sequence[System], experiments: Sequence[Experiment], threads: int = 0
    ) -> list[tuple[FloatArray, FloatArray]]:
        """:func:`simulate_readings_and_commands` of the pairs, the ones seen before looked
        up; a pair repeated within the call is simulated once."""
        keys = [(s, id(e)) for s, e in zip(systems, experiments, strict=True)]
        found: dict[tuple[System, int], tuple[FloatArray, FloatArray]] = {}
        with self._lock:
            for key in keys:
                hit = self._entries.get(key)
                if hit is not None and key not in found:
                    self._entries.move_to_end(key)
                    found[key] = (hit[1], hit[2])
        todo: dict[tuple[System, int], int] = {}
        for j, key in enumerate(keys):
            if key not in found and key not in todo:
                todo[key] = j
        with self._lock:
            self.hits += len(keys) - len(todo)
            self.misses += len(todo)
        if todo:
            idx = list(todo.values())
            sims = simulate_readings_and_commands(
                [systems[j] for j in idx], [experiments[j] for j in idx], threads
            )
            with self._lock:
                for key, j, (reading, command) in zip(todo, idx, sims, strict=True):
                    reading.setflags(write=False)
                    command.setflags(write=False)
                    found[key] = (reading, command)
                    if key not in self._entries:
                        self._entries[key] = (experiments[j], reading, command)
                        self.n_bytes += reading.nbytes + command.nbytes
                while self.n_bytes > self.max_bytes and self._entries:
                    _, (_, r, c) = self._entries.popitem(last=False)
                    self.n_bytes -= r.nbytes + c.nbytes
        return [found[key] for key in keys]


def simulated_mean_reading(system: System, exp: Experiment) -> FloatArray:
    """The simulated true position of the sensor's side minus half a count."""
    return simulate_reading_and_command(system, exp)[0]


def experiment_kind(reference_m: npt.ArrayLike, count_m: float) -> tuple[int, ...]:
    """What makes two experiments comparable in scatter: the sizes of their reference's
    steps in counts, in order, whatever the direction and the start (a 300 nm breakaway test
    and a 1 mm step scatter very differently; a +100 µm and a −100 µm step alike)."""
    d = np.diff(np.asarray(reference_m, dtype=float))
    return tuple(round(abs(float(x)) / count_m) for x in d[d != 0.0])


def _sensor_floor_var(experiments: Sequence[Experiment], count_m: float) -> float:
    """Quantisation ``q²/12`` plus the white sensor noise estimated from the second
    differences of the measured readings where the reference is at rest, m²."""
    noise_var = []
    for e in experiments:
        rest = np.r_[False, np.diff(e.reference_m) == 0] & np.r_[np.diff(e.reference_m) == 0, False]
        d2 = np.diff(e.position_m, 2)
        m = rest[1:-1]
        if np.count_nonzero(m) > 20:
            mad = float(np.median(np.abs(d2[m] - np.median(d2[m]))))
            noise_var.append((1.4826 * mad) ** 2 / 6.0)
    return count_m**2 / 12.0 + (float(np.median(noise_var)) if noise_var else 0.0)


def _repeat_spreads(
    experiments: Sequence[Experiment], count_m: float
) -> list[tuple[tuple[int, ...], float]]:
    """Half the mean-square difference of each pair of repeated experiments (the same
    reference at the same positions: the same step elsewhere on the travel is not a repeat,
    since position-dependent friction makes it differ), with the pair's kind. Measured like
    the gap itself: sample by sample, but in holds as sorted values, so a limit cycle's
    phase (which no model predicts) is not scatter."""
    groups: dict[tuple[int, float], list[Experiment]] = {}
    for e in experiments:
        key = (len(e.reference_m), round(float(e.reference_m[0]) / count_m))
        groups.setdefault(key, []).append(e)
    spreads = []
    for g in groups.values():
        for a, b in itertools.pairwise(g):
            if np.allclose(a.reference_m, b.reference_m, rtol=0.0, atol=count_m / 10):
                r = gap_residual(a.position_m, b.position_m, a.reference_m)
                spreads.append(
                    (experiment_kind(a.reference_m, count_m), float(np.mean(r**2)) / 2.0)
                )
    return spreads


def noise_floor_m(experiments: Sequence[Experiment], count_m: float) -> float:
    """The gap a perfect model would leave, m: quantisation ``q/√12`` plus the white sensor
    noise estimated from the second differences of the measured readings where the
    reference is at rest, raised to the spread of repeated experiments (the same reference
    at the same positions), if any. The spread of two repeats is measured with
    :func:`gap_residual`, as the gap is."""
    return _floors(experiments, count_m)[0]


def _floors(experiments: Sequence[Experiment], count_m: float) -> tuple[float, dict[str, float]]:
    """:func:`noise_floor_m` and :func:`experiment_floors_m` from one pass over the repeats."""
    sensor = _sensor_floor_var(experiments, count_m)
    spreads = _repeat_spreads(experiments, count_m)
    var = sensor
    if spreads:
        # The mean over pairs, like the gap's mean over experiments: experiment types differ
        # in scatter (a chaotic breakaway test far more than a settled step), and a median
        # would report the quiet ones only.
        var = max(var, float(np.mean([v for _, v in spreads])))
    overall = math.sqrt(var)
    by_kind: dict[tuple[int, ...], list[float]] = {}
    for kind, v in spreads:
        by_kind.setdefault(kind, []).append(v)
    own = {}
    for e in experiments:
        vs = by_kind.get(experiment_kind(e.reference_m, count_m))
        own[e.name] = math.sqrt(max(sensor, float(np.mean(vs)))) if vs else overall
    return overall, own


def experiment_floors_m(experiments: Sequence[Experiment], count_m: float) -> dict[str, float]:
    """Each experiment's own noise floor, m: the spread of the repeated experiments of its
    kind (:func:`experiment_kind`; the mean over the kind's repeat pairs), never below the
    sensor floor; an experiment of a kind without repeats gets :func:`noise_floor_m`.

    Experiment types differ in scatter by an order of magnitude (a breakaway test of three
    counts scatters by tens of nm, a 1 mm step or a reversal by hundreds), so one floor for
    all either hides an effect that shows in the quiet experiments only (a rising static
    friction in the breakaway tests) or lets noise in the loud ones pass for an effect."""
    return _floors(experiments, count_m)[1]


@dataclass(frozen=True, slots=True, kw_only=True)
class CandidateResult:
    """One candidate judged on the validation experiments."""

    effect: str
    fit: Fit
    #: The fit of every fold (``fit`` is the first).
    fold_fits: list[Fit]
    #: Mean-square gap per validation experiment (all folds, fold order), m².
    validation_ms: FloatArray
    #: Mean-square command residual per validation experiment, V² (None: no command).
    validation_command_ms: list[float | None]
    #: RMS command residual relative to the model before (None: no measured command).
    command_ratio: float | None
    validation_rms_m: float
    shrink: float
    #: The shrink with each validation experiment weighted by its own noise floor (equal
    #: to ``shrink`` without kind floors): what the complexity penalty is applied to.
    weighted_shrink: float
    p_value: float
    significant: bool
    reasons: list[str]
    setting: int | None = None
    #: The candidate's position in its round (seeds its bootstrap) and its parameter count
    #: (the complexity penalty), kept so that it can be judged again against a new baseline.
    index: int = 0
    k_params: int = 0
    #: Each validation move's share of the mean square (the bootstrap's units).
    validation_units: FloatArray | None = None
    #: Log Occam factor of the candidate's own parameters (:func:`log_occam_factor`).
    log_occam: float = 0.0
    #: Unit of each of the candidate's own parameters (``effect.param`` → unit).
    units: Mapping[str, str] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        units = self.units
        return {
            "effect": self.effect,
            "validation_rms_m": self.validation_rms_m,
            "shrink": self.shrink,
            "weighted_shrink": self.weighted_shrink,
            "significant": self.significant,
            "p_value": self.p_value,
            "command_ratio": self.command_ratio,
            "parameters": {
                n: {"value": v, "std_error": self.fit.std_errors.get(n), "unit": units.get(n)}
                for n, v in self.fit.values.items()
                if n.startswith(self.effect + ".")
            }
            | (
                {f"{self.effect}.samples": {"value": self.setting, "unit": "samples"}}
                if self.setting is not None
                else {}
            ),
            "train_rms_m": self.fit.train_rms_m,
            "log_occam_factor": self.log_occam,
            "validation_rms_by_experiment_m": [float(math.sqrt(m)) for m in self.validation_ms],
            "why": self.reasons,
        }


def _bootstrap_p(d: FloatArray, n_boot: int, seed: int) -> float:
    """Fraction of bootstrap resamples (of the units: validation moves) with mean reduction
    ≤ 0."""
    if len(d) == 0:
        return 1.0
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(d), size=(n_boot, len(d)))
    means = d[idx].mean(axis=1)
    return float(np.mean(means <= 0.0))


def indistinguishable(a: CandidateResult, b: CandidateResult) -> bool:
    """Whether the validation data cannot tell candidates ``a`` and ``b`` apart: their RMS
    gaps lie within 25 % of each other and the mean difference of their per-experiment mean
    squares is within two standard errors (over the validation experiments). With fewer
    than two validation experiments nothing can be told apart."""
    d = a.validation_ms - b.validation_ms
    if len(d) < 2:
        return True
    se = float(np.std(d, ddof=1) / math.sqrt(len(d)))
    close = abs(a.validation_rms_m - b.validation_rms_m) <= 0.25 * min(
        a.validation_rms_m, b.validation_rms_m
    )
    return close and abs(float(np.mean(d))) <= 2.0 * se


def log_occam_factor(fit: Fit, names: Sequence[str], n_settings: int = 0) -> float:
    """Log of the Occam factor of a candidate's own parameters (their ``names`` in
    ``fit.values``): the factor by which the Laplace approximation of the Bayesian
    evidence, with a uniform prior on the parameters' bounds, falls short of the best fit's
    likelihood, minus log ``n_settings`` for a discrete candidate (one of its settings).

    In the fit's normalised coordinates every parameter's bounds span 1 (log space for a
    log parameter), so the factor is the posterior's volume √det(2πΣ), Σ the marginal
    covariance of the candidate's own parameters (:attr:`Fit.unit_covariance`): small when
    the data pin the parameters down to a sliver of their plausible ranges. Correlated
    parameters pin down less volume than their standard errors alone say (√(1−ρ²) for two).
    Each principal direction counts at most its whole range: ½ Σⱼ log min(1, 2πλⱼ) over
    the eigenvalues λⱼ of Σ. A parameter the data do not constrain (variance 0 from the
    pseudo-inverse, or not finite), and a direction of Σ with a numerically zero variance,
    count as their whole range (factor 1)."""
    out = -math.log(n_settings) if n_settings > 1 else 0.0
    fitted = list(fit.values)
    cov = fit.unit_covariance
    if cov.shape != (len(fitted), len(fitted)):
        return out  # no covariance (the standard errors are not finite either)
    idx = [fitted.index(n) for n in names if n in fit.values]
    sub = cov[np.ix_(idx, idx)]
    keep = [
        i
        for i in range(len(idx))
        if sub[i, i] > 0.0 and bool(np.all(np.isfinite(sub[i])) and np.all(np.isfinite(sub[:, i])))
    ]
    if not keep:
        return out
    sub = sub[np.ix_(keep, keep)]
    lam = np.linalg.eigvalsh(sub)
    tiny = float(np.max(lam)) * len(keep) * np.finfo(np.float64).eps
    for v in lam:
        if v > tiny:
            out += 0.5 * math.log(min(1.0, 2.0 * math.pi * float(v)))
    return out


def pick_winner(
    results: Sequence[CandidateResult], st: DiagnosisSettings
) -> CandidateResult | None:
    """The candidate a round selects from its results (best validation gap first): the
    first significant one; with :attr:`DiagnosisSettings.occam_tie_break`, among it and the
    significant candidates the data cannot tell from it, the one with the largest Occam
    factor (the first in gap order when equal). None when nothing is significant."""
    best = next((r for r in results if r.significant), None)
    if best is None or not st.occam_tie_break:
        return best
    group = [r for r in results if r.significant and (r is best or indistinguishable(best, r))]
    return max(group, key=lambda r: r.log_occam)


FRICTION_MODELS = ("coulomb_viscous", "stribeck", "dahl", "lugre", "gms")

#: A train/validate split of experiments.
Split = tuple[Sequence[Experiment], Sequence[Experiment]]


@dataclass(frozen=True, slots=True, kw_only=True)
class _Ctx:
    free: Sequence[tuple[str, Param]]
    set_free: Callable[[System, Mapping[str, float]], System]
    folds: Sequence[Split]
    floor: float
    st: DiagnosisSettings
    adapt: Adapt
    #: The nominal model the free parameters are set on.
    nominal: System
    #: Warm start of the free nominal parameters per fold (updated after each round).
    warm: list[dict[str, float]] = field(default_factory=list)
    #: Effects selected so far, with their fitted values, in order.
    selected_effects: list[tuple[Candidate, list[float]]] = field(default_factory=list)
    #: Per experiment name: (overall floor / its own floor)², the weight of its mean square
    #: in the significance rules (missing: 1).
    weights: Mapping[str, float] = field(default_factory=dict)
    #: Simulations of this diagnosis kept for reuse (None: every one simulated).
    cache: SimulationCache | None = None

    @property
    def n_validation(self) -> int:
        return sum(len(v) for _, v in self.folds)

    @property
    def validation_weights(self) -> FloatArray:
        """The weight of each validation experiment, in the order of the validation mean
        squares (folds concatenated)."""
        return np.array([self.weights.get(e.name, 1.0) for _, v in self.folds for e in v])

    def builder(
        self, base: System, apply_extra: Callable[[System, Sequence[float]], System]
    ) -> Callable[[Sequence[float]], System]:
        nf = len(self.free)

        def build(values: Sequence[float]) -> System:
            # The free nominal parameters first, then the effects selected so far (with
            # their fitted values), then the candidate: an effect may depend on a free
            # parameter (e.g. a drive-side mass as a ratio of the table mass).
            s = self.set_free(
                self.nominal, {n: v for (n, _), v in zip(self.free, values[:nf], strict=True)}
            )
            for cand, vals in self.selected_effects:
                s = cand.apply(s, vals)
            return apply_extra(s, values[nf:])

        return build

    def best_start_setting(self, base: System, cand: Candidate) -> tuple[int, ...]:
        """The setting of a discrete candidate whose model at the start of its fits (each
        fold's warm free values, and the manifest's values) has the smallest training gap,
        summed over folds, as a one-element tuple; all its settings when every start fails
        to simulate (their fits then report why). All the settings' starts of a fold are
        simulated as one batch."""
        cost = np.zeros(len(cand.discrete))
        prior = {n: p.initial for n, p in self.free}
        for i, (train, _) in enumerate(self.folds):
            warm = self.warm[i] if i < len(self.warm) else prior
            starts = [warm] if warm == prior else [warm, prior]
            systems = [
                self.builder(base, _at_setting(cand, k))([st[n] for n, _ in self.free])
                for k in cand.discrete
                for st in starts
            ]
            # Only its batch evaluation is used: the systems are built above.
            prob = FitProblem(
                self.free, lambda v: base, train, self.st.workers, self.adapt, self.cache
            )
            ms = [math.inf if r is None else _rms(r) ** 2 for r in prob.residuals_or_none(systems)]
            cost += np.min(np.reshape(ms, (len(cand.discrete), len(starts))), axis=1)
        if not np.isfinite(cost).any():
            return cand.discrete
        return (cand.discrete[int(np.argmin(cost))],)

    def fit_and_validate(
        self,
        base: System,
        params: Sequence[tuple[str, Param]],
        apply_extra: Callable[[System, Sequence[float]], System],
        n_starts: int,
        seed: int,
        screen: bool = False,
        scan_points: int | None = None,
        screen_starts: int = 1,
        scan_starts: int = 1,
    ) -> tuple[list[Fit], FloatArray, list[list[FloatArray]], list[float | None], FloatArray]:
        """Fit on each fold's training experiments; mean-square gap on its validation ones
        (concatenated over folds), the validation residuals per fold, the mean-square
        command residual of each validation experiment (None without a measured command),
        and each validation move's share of its experiment's mean square (:func:`move_units`;
        they sum to the experiment's)."""
        fits, ms, residuals = [], [], []
        units: list[float] = []
        command: list[float | None] = []
        for i, (train, validate) in enumerate(self.folds):
            warm = self.warm[i] if i < len(self.warm) else {}
            free = [
                (n, dataclasses.replace(p, initial=warm[n]) if n in warm else p)
                for n, p in self.free
            ]
            prob = FitProblem(
                free + list(params),
                self.builder(base, apply_extra),
                train,
                self.st.workers,
                self.adapt,
                self.cache,
            )
            # Two starts at least: the warm values, and the manifest's (prior) values.
            prior = [p.initial for _, p in self.free] + [p.initial for _, p in params]
            # Screening uses the warm start only, except for candidates without continuous
            # parameters (delays), whose changes can move the free parameters far: they
            # also get the prior start.
            both = warm and (not screen or not params)
            f = prob.fit(
                (max(n_starts, 2) if both else screen_starts) if screen or warm else n_starts,
                self.st,
                seed,
                n_warm=len(free) if warm else 0,
                prior=prior if both else None,
                # The first calibration of the model (no warm values) scans all its free
                # parameters: it is cheap, and a poor local optimum there would make any
                # candidate's refit look like an effect.
                scan=(
                    scan_points or min(self.st.scan_points * len(params), self.st.scan_points_max)
                )
                if params
                else (0 if warm else self.st.scan_points_nominal),
                scan_starts=scan_starts,
            )
            res, val_command = prob.residuals_and_commands(f.system, validate)
            fits.append(f)
            residuals.append(res)
            ms += [float(np.mean(r**2)) for r in res]
            for e, r in zip(validate, res, strict=True):
                w = self.weights.get(e.name, 1.0)
                units += [
                    w * float(np.sum(r[a:b] ** 2)) / len(r) for a, b in move_units(e.reference_m)
                ]
            command += val_command
        return fits, np.array(ms), residuals, command, np.array(units)


def diagnose_experiments(
    nominal: System,
    free: Sequence[tuple[str, Param]],
    set_free: Callable[[System, Mapping[str, float]], System],
    folds: Sequence[Split],
    *,
    adapt: Adapt | None = None,
    candidates: Sequence[str] | None = None,
    settings: DiagnosisSettings | None = None,
    progress: bool = True,
) -> dict[str, Any]:
    """Run the diagnosis over train/validate folds. Returns a dict with ``nominal`` (Fit of
    the first fold), ``nominal_validation_ms``, ``floor_rms_m``, ``rounds`` (lists of
    CandidateResult, best first), ``selected`` (names), ``final`` (Fit of the first fold),
    ``final_validation_ms``, ``skipped`` (name → reason), ``refit_control`` (the rounds in
    which refitting the model before from a candidate's free values improved it),
    ``timing_s``, ``simulations`` (``simulated``: simulations run, None without the
    cache; ``reused``: looked up in the :class:`SimulationCache`) and ``cache`` (that
    cache, or None: the report's simulations of the same fits look it up)."""
    st = settings or DiagnosisSettings()
    t_start = time.perf_counter()
    if not st.simulation_cache_mb >= 0.0:
        raise ValueError(
            f"DiagnosisSettings.simulation_cache_mb = {st.simulation_cache_mb!r}: must be ≥ 0 "
            "(MB of simulations kept for reuse; 0 turns the reuse off)"
        )
    if not folds or any(len(v) == 0 for _, v in folds):
        raise ValueError("the diagnosis needs at least one validation experiment per fold")
    every = {e.name: e for tr, va in folds for e in list(tr) + list(va)}
    floor, floors = _floors(list(every.values()), nominal.encoder.count_m)
    weights = {n: (floor / f) ** 2 for n, f in floors.items()} if st.kind_floors else {}
    # Candidate names and start values are checked before any fitting.
    cands, skipped = applicable_candidates(nominal, candidates)
    cands = with_starts(cands, st.candidate_starts)
    unknown = sorted(set(st.candidate_starts or {}) - {c.name for c in cands})
    if unknown:
        raise ValueError(
            f"candidate_starts names {', '.join(map(repr, unknown))}, not among the "
            f"candidates of this diagnosis ({', '.join(c.name for c in cands)})"
        )
    ctx = _Ctx(
        free=free,
        set_free=set_free,
        folds=folds,
        floor=floor,
        st=st,
        weights=weights,
        adapt=adapt or (lambda s, e: s),
        nominal=nominal,
        cache=(
            SimulationCache(st.simulation_cache_mb * 1e6) if st.simulation_cache_mb > 0 else None
        ),
    )
    _progress(
        f"diagnosis: calibrating the nominal model ({len(free)} free parameters, "
        f"{len(folds)} fold(s))",
        progress,
    )
    nominal_fits, base_ms, _, base_cmd, base_units = ctx.fit_and_validate(
        nominal, (), lambda s, v: s, st.n_starts_nominal, st.seed
    )
    ctx.warm[:] = [_free_values(f, free) for f in nominal_fits]
    selected: list[str] = []
    rounds: list[list[CandidateResult]] = []
    refits: list[dict[str, Any]] = []
    current = nominal
    current_fits = nominal_fits
    current_ms = base_ms
    current_cmd = base_cmd
    current_units: FloatArray | None = base_units
    pool_names = [c.name for c in cands]
    for rnd in range(st.forward_rounds):
        names = pool_names if rnd == 0 else pool_names[: st.forward_top]
        cand_now, _ = applicable_candidates(current, [n for n in names if n not in selected])
        cand_now = with_starts(cand_now, st.candidate_starts)
        if any(n in FRICTION_MODELS for n in selected):
            cand_now = [c for c in cand_now if c.name not in FRICTION_MODELS]
        results: list[CandidateResult] = []

        now = (current, current_ms, current_cmd, current_units)
        for i, cand, r, exc, seconds in _concurrently(
            list(enumerate(cand_now)), now, ctx, screen=True
        ):
            if r is None:
                # An invalid combination with the effects already selected, or a
                # simulation failing at the start values: reported, not fatal.
                skipped[cand.name] = f"round {rnd + 1}: could not be fitted: {exc}"
                _progress(f"  round {rnd + 1} {cand.name}: not fitted ({exc})", progress)
                continue
            results.append(r)
            _progress(
                f"  round {rnd + 1} [{i + 1}/{len(cand_now)}] {cand.name:26s} "
                f"validation {r.validation_rms_m * 1e9:9.1f} nm  shrink {r.shrink:+.1%}"
                f"{'  significant' if r.significant else ''}"
                f"  ({seconds:.1f} s)",
                progress,
            )
        results.sort(key=lambda r: r.validation_rms_m)
        # Refine the best few with all starts (warm, the manifest's prior, Latin
        # hypercube), then rank again.
        by_name = {c.name: (i, c) for i, c in enumerate(cand_now)}

        top = [by_name[name] for name in refine_names(results, st)]
        where = {r.effect: j for j, r in enumerate(results)}
        for _, cand, refined, exc, seconds in _concurrently(top, now, ctx, screen=False):
            if refined is None:
                skipped[cand.name] = f"round {rnd + 1}: refit failed: {exc}"
                continue
            results[where[cand.name]] = refined
            _progress(
                f"  round {rnd + 1} refit {cand.name:26s} validation "
                f"{refined.validation_rms_m * 1e9:9.1f} nm  shrink {refined.shrink:+.1%}"
                f"{'  significant' if refined.significant else ''}"
                f"  ({seconds:.1f} s)",
                progress,
            )
        results.sort(key=lambda r: r.validation_rms_m)
        # Refitting alone: a candidate's fit moves the free nominal parameters too, and
        # may have found a better optimum of the model *without* the effect. Refit the
        # model before from each significant candidate's free values; a better
        # training fit becomes the baseline, and every candidate is judged again.
        better = _refit_control(ctx, current, results, current_fits, current_ms, rnd, progress)
        if better is not None:
            current_fits, current_ms, current_cmd, current_units, record = better
            refits.append(record)
            ctx.warm[:] = [_free_values(f, free) for f in current_fits]
            if rnd == 0:
                nominal_fits, base_ms = current_fits, current_ms
            # Judged again against the new baseline; what does not depend on it (the
            # Occam factor, the units) is carried over.
            results = [
                dataclasses.replace(
                    _verdict(
                        r.effect,
                        r.fold_fits,
                        r.validation_ms,
                        r.validation_command_ms,
                        r.setting,
                        r.k_params,
                        current_ms,
                        current_cmd,
                        ctx,
                        r.index,
                        r.validation_units,
                        current_units,
                    ),
                    log_occam=r.log_occam,
                    units=r.units,
                )
                for r in results
            ]
            results.sort(key=lambda r: r.validation_rms_m)
        rounds.append(results)
        if rnd == 0:
            pool_names = [r.effect for r in results]
        best = pick_winner(results, st)
        if best is None:
            break
        selected.append(best.effect)
        cand_best = next(c for c in cand_now if c.name == best.effect)
        values = _effect_values(cand_best, best)
        ctx.selected_effects.append((cand_best, values))
        current = cand_best.apply(current, values)
        current_fits = best.fold_fits
        ctx.warm[:] = [_free_values(f, free) for f in best.fold_fits]
        current_ms = best.validation_ms
        current_cmd = best.validation_command_ms
        current_units = best.validation_units
    return {
        "nominal": nominal_fits[0],
        "nominal_fits": nominal_fits,
        "nominal_validation_ms": base_ms,
        "floor_rms_m": floor,
        "experiment_floors_m": floors,
        "kind_floors": st.kind_floors,
        "rounds": rounds,
        "selected": selected,
        "selected_effects": list(ctx.selected_effects),
        "final": current_fits[0],
        "final_fits": current_fits,
        "final_validation_ms": current_ms,
        "skipped": skipped,
        "refit_control": refits,
        "timing_s": time.perf_counter() - t_start,
        "cache": ctx.cache,
        "simulations": {
            "simulated": None if ctx.cache is None else ctx.cache.misses,
            "reused": 0 if ctx.cache is None else ctx.cache.hits,
        },
    }


def refine_names(results: Sequence[CandidateResult], st: DiagnosisSettings) -> list[str]:
    """The candidates of a round refitted from all starts, from its screened results (best
    first): the best :attr:`DiagnosisSettings.refine_top`, and with
    :attr:`DiagnosisSettings.refine_best_friction_model` the best-screened friction-model
    candidate outside them (one at most)."""
    names = [r.effect for r in results[: st.refine_top]]
    if st.refine_best_friction_model:
        rest = (r.effect for r in results[st.refine_top :] if r.effect in FRICTION_MODELS)
        best = next(rest, None)
        if best is not None:
            names.append(best)
    return names


def _concurrently(
    items: Sequence[tuple[int, Candidate]],
    now: tuple[System, FloatArray, Sequence[float | None], FloatArray | None],
    ctx: _Ctx,
    screen: bool,
) -> Iterator[tuple[int, Candidate, CandidateResult | None, Exception | None, float]]:
    """:func:`_judge` of each ``(index, candidate)`` against the model ``now`` (system,
    validation mean squares, command residuals, move units), up to
    ``ctx.st.parallel_candidates`` at a time, yielded in the order given:
    ``(i, cand, result, None, seconds)``, or ``(i, cand, None, error, seconds)`` for a
    candidate that could not be fitted (``ValueError``/``RuntimeError``). The candidates'
    fits are independent (each its own problem, starts and seed), so the results do not
    depend on how many run at once: two at once overlap one fit's Python work with the
    other's simulations (which release the GIL)."""

    def one(item: tuple[int, Candidate]) -> tuple[CandidateResult | None, Exception | None, float]:
        t0 = time.perf_counter()
        try:
            r = _judge(item[1], *now, ctx, item[0], screen=screen)
        except (ValueError, RuntimeError) as exc:
            return None, exc, time.perf_counter() - t0
        return r, None, time.perf_counter() - t0

    threads = max(1, min(ctx.st.parallel_candidates, len(items)))
    with ThreadPoolExecutor(max_workers=threads) as pool:
        outcomes = pool.map(one, items) if threads > 1 else map(one, items)
        for (i, cand), (r, exc, dt) in zip(items, outcomes, strict=True):
            yield i, cand, r, exc, dt


def crossfit_folds(n_train: int, n_validate: int, k: int) -> list[tuple[list[int], list[int]]]:
    """The folds of :func:`crossfit_models`: ``(training indices, judged indices)`` into the
    list training + validation experiments. Fold ``j`` judges the validation experiments
    ``j, j + k, j + 2k, …`` and trains on every other experiment (round robin, so that each
    fold holds a mix of the validation kinds); every validation experiment is judged once."""
    k = max(1, min(k, n_validate))
    out = []
    for j in range(k):
        judged = [n_train + i for i in range(j, n_validate, k)]
        out.append(([i for i in range(n_train + n_validate) if i not in judged], judged))
    return out


def crossfit_models(
    nominal: System,
    free: Sequence[tuple[str, Param]],
    set_free: Callable[[System, Mapping[str, float]], System],
    train: Sequence[Experiment],
    validate: Sequence[Experiment],
    effects: Sequence[tuple[Candidate, Sequence[float]]],
    warm_nominal: Mapping[str, float],
    warm_final: Mapping[str, float],
    *,
    k: int,
    adapt: Adapt,
    settings: DiagnosisSettings,
    cache: SimulationCache | None = None,
) -> list[tuple[list[Experiment], System, System]]:
    """Cross-fitting of the nominal and the selected model over the validation experiments:
    for each fold of :func:`crossfit_folds`, both models are refitted (one local fit from
    the diagnosis's fitted values: the free nominal parameters, and for the selected model
    also every selected effect's continuous parameters; a delay keeps its setting) on the
    training experiments plus the other folds' validation experiments. Returns, per fold,
    the experiments it judges and the two refitted systems. Each validation experiment is
    judged by models whose fit never saw it, fitted on nearly all the data, as a user would
    recalibrate before using the model: the gap they leave is the shrink to expect then.
    With ``cache`` (the diagnosis's), the folds' shared simulations (the first Jacobian at
    the common warm start, on the experiments the folds have in common) are looked up."""
    exps = list(train) + list(validate)
    nf = len(free)

    def problem(
        training: list[Experiment],
        warm: Mapping[str, float],
        with_effects: Sequence[tuple[Candidate, Sequence[float]]],
    ) -> FitProblem:
        params = [(n, dataclasses.replace(p, initial=warm[n])) for n, p in free]
        for cand, values in with_effects:
            if not cand.discrete:
                params += [
                    (f"{cand.name}.{q.name}", dataclasses.replace(q, initial=float(v)))
                    for q, v in zip(cand.params, values, strict=True)
                ]

        def build(values: Sequence[float]) -> System:
            s = set_free(nominal, {n: v for (n, _), v in zip(free, values[:nf], strict=True)})
            at = nf
            for cand, fitted in with_effects:
                if cand.discrete:
                    s = cand.apply(s, fitted)
                else:
                    s = cand.apply(s, values[at : at + len(cand.params)])
                    at += len(cand.params)
            return s

        return FitProblem(params, build, training, settings.workers, adapt, cache)

    jobs = []
    for tr, judged in crossfit_folds(len(train), len(validate), k):
        training = [exps[i] for i in tr]
        jobs.append((training, [exps[i] for i in judged]))

    def fit_pair(job: tuple[list[Experiment], list[Experiment]]) -> tuple[System, System]:
        training, _ = job
        before = problem(training, warm_nominal, ()).fit(1, settings, settings.seed)
        after = (
            problem(training, warm_final, effects).fit(1, settings, settings.seed)
            if effects
            else before
        )
        return before.system, after.system

    threads = max(1, min(settings.parallel_candidates, len(jobs)))
    with ThreadPoolExecutor(max_workers=threads) as pool:
        pairs = list(pool.map(fit_pair, jobs) if threads > 1 else map(fit_pair, jobs))
    return [(judged, b, a) for (_, judged), (b, a) in zip(jobs, pairs, strict=True)]


def _refit_control(
    ctx: _Ctx,
    current: System,
    results: Sequence[CandidateResult],
    current_fits: Sequence[Fit],
    current_ms: FloatArray,
    rnd: int,
    progress: bool,
) -> tuple[list[Fit], FloatArray, list[float | None], FloatArray, dict[str, Any]] | None:
    """The model before, refitted from the free values of each of the best
    ``refit_control_top`` significant candidates (None: all): its fits, validation mean squares,
    command residuals and a record for the report if one of them fits the training data
    better than ``current_fits`` (by more than 0.1 % in mean square), else None."""
    st = ctx.st
    if not ctx.free or (st.refit_control_top is not None and st.refit_control_top <= 0):
        return None
    saved = list(ctx.warm)

    def train_ms(fits: Sequence[Fit]) -> float:
        return float(np.mean([f.train_rms_m**2 for f in fits]))

    best: tuple[list[Fit], FloatArray, list[float | None], FloatArray, dict[str, Any]] | None = None
    before = train_ms(current_fits)
    best_train = before * (1.0 - 1e-3)
    try:
        for r in [r for r in results if r.significant][: st.refit_control_top]:
            ctx.warm[:] = [_free_values(f, ctx.free) for f in r.fold_fits]
            fits, ms, _, cmd, units = ctx.fit_and_validate(current, (), lambda s, v: s, 1, st.seed)
            t = train_ms(fits)
            _progress(
                f"  round {rnd + 1} refit control from {r.effect}'s free values: training "
                f"{math.sqrt(t) * 1e9:.1f} nm (before {math.sqrt(before) * 1e9:.1f})",
                progress,
            )
            if t < best_train:
                record = {
                    "round": rnd + 1,
                    "restarted_from": r.effect,
                    "train_rms_before_m": math.sqrt(before),
                    "train_rms_after_m": math.sqrt(t),
                    "validation_rms_before_m": math.sqrt(float(np.mean(current_ms))),
                    "validation_rms_after_m": math.sqrt(float(np.mean(ms))),
                }
                best, best_train = (fits, ms, cmd, units, record), t
    finally:
        ctx.warm[:] = saved
    return best


def _free_values(fit: Fit, free: Sequence[tuple[str, Param]]) -> dict[str, float]:
    return {n: fit.values[n] for n, _ in free if n in fit.values}


def _effect_values(cand: Candidate, best: CandidateResult) -> list[float]:
    """The winner's fitted effect values (its integer setting for a delay)."""
    if cand.discrete:
        assert best.setting is not None
        return [float(best.setting)]
    return [best.fit.values[f"{cand.name}.{p.name}"] for p in cand.params]


def _at_setting(cand: Candidate, k: int) -> Callable[[System, Sequence[float]], System]:
    """A discrete candidate's ``apply`` fixed at setting ``k`` (it takes no values)."""

    def apply(s: System, v: Sequence[float]) -> System:
        return cand.apply(s, [k])

    return apply


def _judge(
    cand: Candidate,
    base: System,
    base_ms: FloatArray,
    base_cmd: Sequence[float | None],
    base_units: FloatArray | None,
    ctx: _Ctx,
    index: int,
    screen: bool = False,
) -> CandidateResult:
    """Fit one candidate on every fold and judge it on the validation experiments
    (``screen``: one warm start only, for ranking)."""
    st = ctx.st
    extra = [(f"{cand.name}.{p.name}", p) for p in cand.params]
    setting: int | None = None
    if cand.discrete:
        best: tuple[list[Fit], FloatArray, list[float | None], int, FloatArray] | None = None
        # Screening fits only the setting whose start fits the training experiments best
        # (each setting's fit costs as much as a whole continuous candidate's); refining
        # fits every setting.
        ks = ctx.best_start_setting(base, cand) if screen else cand.discrete
        for k in ks:
            fits, ms, _, cmd, units = ctx.fit_and_validate(
                base, (), _at_setting(cand, k), 1, st.seed + index, screen
            )
            train = float(np.mean([f.train_rms_m for f in fits]))
            if best is None or train < float(np.mean([f.train_rms_m for f in best[0]])):
                best = (fits, ms, cmd, k, units)
        assert best is not None
        fits, ms, cmd, setting, units = best
        k_params = 1
    else:
        friction_model = cand.name in FRICTION_MODELS
        # The extra starts of a friction model in the first round only: later rounds ask
        # whether anything remains on top of the selected effects, whose simulations can
        # cost far more (a hunting backlash ~16×).
        many = friction_model and not ctx.selected_effects
        fits, ms, _, cmd, units = ctx.fit_and_validate(
            base,
            extra,
            cand.apply,
            st.n_starts_friction_models if many else st.n_starts_candidate,
            st.seed + index,
            screen,
            cand.scan_points,
            # A friction-model candidate replaces the table friction, so its warm start is
            # not the model before: screen it from the warm start and the scan's best.
            st.screen_starts_friction_models if friction_model else 1,
            cand.scan_starts,
        )
        k_params = len(cand.params)
    result = _verdict(
        cand.name,
        fits,
        ms,
        cmd,
        setting,
        k_params,
        base_ms,
        base_cmd,
        ctx,
        index,
        units,
        base_units,
    )
    return dataclasses.replace(
        result,
        log_occam=log_occam_factor(fits[0], [n for n, _ in extra], len(cand.discrete)),
        units={n: p.unit for n, p in extra},
    )


def _verdict(
    name: str,
    fits: list[Fit],
    ms: FloatArray,
    cmd: list[float | None],
    setting: int | None,
    k_params: int,
    base_ms: FloatArray,
    base_cmd: Sequence[float | None],
    ctx: _Ctx,
    index: int,
    units: FloatArray | None = None,
    base_units: FloatArray | None = None,
) -> CandidateResult:
    """Judge fitted candidate results against the model before (``base_ms``). The bootstrap
    resamples validation moves (``units``/``base_units``) when both are given, else
    experiments."""
    st = ctx.st
    d = base_ms - ms
    # The rules weigh each validation experiment by its own noise floor (all 1 without
    # kind floors): in units of the overall floor, a quiet experiment's gap counts as much
    # as a loud one's relative to what noise alone gives there. The move units come
    # weighted from :meth:`_Ctx.fit_and_validate`.
    w = ctx.validation_weights if len(base_ms) == ctx.n_validation else np.ones(len(base_ms))
    du = (
        base_units - units
        if units is not None and base_units is not None and len(units) == len(base_units)
        else w * d
    )
    p = _bootstrap_p(du, st.bootstrap, st.seed + 1000 + index)
    rms0 = math.sqrt(float(np.mean(base_ms)))
    rms1 = math.sqrt(float(np.mean(ms)))
    shrink = 1.0 - rms1 / rms0 if rms0 > 0 else 0.0
    wrms0 = math.sqrt(float(np.mean(w * base_ms)))
    wrms1 = math.sqrt(float(np.mean(w * ms)))
    weighted_shrink = 1.0 - wrms1 / wrms0 if wrms0 > 0 else 0.0
    penalty = st.penalty_base + st.penalty_per_param * k_params
    floor_gain = st.floor_factor * ctx.floor**2 / ctx.n_validation
    gain = float(np.mean(w * d))
    weighted = bool(np.any(w != 1.0))
    wtag = " (floor-weighted)" if weighted else ""
    reasons = []
    ok = True
    if p >= st.p_value:
        ok = False
        reasons.append(f"bootstrap over validation moves{wtag}: p = {p:.2f} ≥ {st.p_value}")
    if weighted_shrink <= penalty:
        ok = False
        reasons.append(f"shrink{wtag} {weighted_shrink:.1%} ≤ complexity penalty {penalty:.0%}")
    if wrms0 <= st.explainable_factor * ctx.floor:
        ok = False
        reasons.append(
            f"the gap before{wtag} ({wrms0 * 1e9:.0f} nm) is within {st.explainable_factor}× "
            f"the noise floor ({ctx.floor * 1e9:.0f} nm): nothing left to explain"
        )
    if gain <= floor_gain:
        ok = False
        reasons.append(
            f"mean-square gain {gain:.3g} m² ≤ noise-and-refit floor {floor_gain:.3g} m²"
        )
    pairs = [(a, b) for a, b in zip(base_cmd, cmd, strict=True) if a is not None and b is not None]
    command_ratio = (
        math.sqrt(sum(b for _, b in pairs) / sum(a for a, _ in pairs))
        if pairs and sum(a for a, _ in pairs) > 0
        else None
    )
    if command_ratio is not None and command_ratio > st.command_tolerance:
        ok = False
        reasons.append(
            f"the measured command (a channel the fit does not use) gets worse: its RMS "
            f"residual × {command_ratio:.2f}"
        )
    if ok:
        reasons.append(
            f"validation gap {rms0 * 1e9:.0f} → {rms1 * 1e9:.0f} nm (shrink {shrink:.0%}"
            + (f"; floor-weighted {wrms0 * 1e9:.0f} → {wrms1 * 1e9:.0f} nm" if weighted else "")
            + f"), bootstrap p = {p:.3f}"
            + ("" if command_ratio is None else f", command residual × {command_ratio:.2f}")
        )
    return CandidateResult(
        effect=name,
        fit=fits[0],
        fold_fits=fits,
        validation_ms=ms,
        validation_command_ms=cmd,
        command_ratio=command_ratio,
        validation_rms_m=rms1,
        shrink=shrink,
        weighted_shrink=weighted_shrink,
        p_value=p,
        significant=ok,
        reasons=reasons,
        setting=setting,
        index=index,
        k_params=k_params,
        validation_units=units,
    )
