"""The diagnosis loop: calibrate the nominal model, fit every candidate effect on the
training experiments, judge it on the validation experiments, select effects forward, and
cross-fit the chosen model over folds."""

from __future__ import annotations

import dataclasses
import math
import time
import zlib
from collections.abc import Callable, Iterator, Mapping, Sequence
from concurrent.futures import Executor, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from ..blas import keep_one_blas_thread, single_threaded_blas
from ..checks import executor_arg
from ..config import System
from ..experiment import Experiment
from .candidates import Candidate, Param, applicable_candidates
from .fit import Fit, FitProblem, at_bounds
from .objective import (
    MICRO_STEP_MAX_COUNTS,
    SimulationCache,
    channel_units,
    command_floors_v,
    command_problems,
    floors_m,
    move_units,
    proportional_gain_v_per_m,
    ramp_intervals,
    rms_of,
)
from .scatter import LevelScatter, level_floors, level_scatter_directions, level_sensitivities
from .select import (
    CandidateResult,
    bootstrap_p,
    holm_levels,
    log_occam_factor,
    null_test_p,
    pick_winner,
    rank_key,
    relative_terms,
    significance_mode,
    turned_down,
    widens_pooled_gap,
    without_unsupported,
)
from .settings import (
    Adapt,
    DiagnosisSettings,
    FloatArray,
    PhaseClock,
    print_progress,
    with_starts,
)
from .signatures import SignatureJudge, chi_square, misses

FRICTION_MODELS = ("coulomb_viscous", "stribeck", "dahl", "lugre", "gms")
#: The effects that add lag or play to the loop (limit cycles, phase lag): refined as a
#: family when the model before has a free parameter at its bound or misses one of the
#: marks they make (:attr:`DiagnosisSettings.refine_lag_family_at_bounds`,
#: :attr:`DiagnosisSettings.refine_on_missed_marks`, :func:`mark_effects`).
LAG_FAMILY = (
    "backlash",
    "computation_delay",
    "sensor_delay",
    "drive_compliance",
    "amplifier_dynamics",
)

#: The effects that shift the sliding force by direction: an offset force and a direction
#: asymmetry of the friction levels are aliases while sliding (a bias of F₀ against one of
#: a·Fc) and differ only at rest and at breakaway. When either is refined, so is the other
#: (:attr:`DiagnosisSettings.refine_bias_aliases`), so that the two are told apart at equal
#: effort rather than by which one screened better.
BIAS_ALIASES = ("offset_force", "asymmetric_friction")

#: The marks of the traces (:mod:`~nanostage.diagnosis.signatures`) that only a force
#: shifting both directions alike makes: the mean of the two directions' commands, on
#: ramps and at rest. A symmetric friction law, a lag or a play leaves them at zero
#: whatever its parameters; an offset force or a direction asymmetry of the friction
#: levels sets them (:func:`mark_effects`).
BIAS_MARKS = ("ramp_bias_v", "rest_command_mean_v")
#: The mark of dwell-dependent breakaway: the rise of a move's peak command per decade
#: of the rest before it (:func:`mark_effects`).
BREAKAWAY_MARKS = ("breakaway_per_decade_v",)

#: The marks of the friction's dependence on speed: the steady command on constant-velocity
#: ramps extrapolated to rest and its rise with speed. A friction law that falls with speed
#: (a Stribeck drop) or rises with it (viscous friction) moves them, and a presliding law's
#: form error (how the force builds up within a few micrometres of a reversal) does not
#: reach a ramp's steady sliding (:func:`speed_mark_support`). Any candidate's refit of the
#: free nominal parameters can move them too (on consumed case 1520008 a backlash's refit
#: removed 70 % of their χ²): they exempt a friction law from the share rule, they do not
#: prove it right.
SPEED_MARKS = ("ramp_level_v", "ramp_slope_v_s_per_m")

#: A train/validate split of experiments.
Split = tuple[Sequence[Experiment], Sequence[Experiment]]

__all__ = [
    "cross_judge_split",
    "crossfit_folds",
    "crossfit_models",
    "diagnose_experiments",
    "experiment_class",
    "mark_effects",
    "refine_names",
    "speed_mark_support",
]


#: Singular values of the free nominal parameters' Jacobian below this share of the
#: largest are left out of :class:`NominalStep` (directions the training experiments do
#: not constrain).
NOMINAL_STEP_RCOND = 1e-6


@dataclass(frozen=True, slots=True, kw_only=True)
class NominalStep:
    """The free nominal parameters' Jacobian of a model before's scaled training residual,
    at their values ``unit`` (normalised coordinates), as a thin singular value
    decomposition ``basis · diag(singular) · rightᵀ`` (:meth:`_Ctx._nominal_step`)."""

    unit: FloatArray
    basis: FloatArray
    singular: FloatArray
    right: FloatArray


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
    #: Weight of the command gap against the position gap in every fit and judgement, m/V,
    #: per experiment by name (none: the command is not part of the gap;
    #: :func:`command_weights`).
    command_weights_m_per_v: Mapping[str, float] = field(default_factory=dict)
    #: The direction of a run-to-run friction level change in each experiment's gap and
    #: the factor its component is kept by, per experiment by name (none: every gap as it
    #: is; :mod:`~nanostage.diagnosis.scatter`).
    level_directions: Mapping[str, tuple[FloatArray, float]] = field(default_factory=dict)
    #: How many candidates are judged together (a round's, or its cross-judging's): the
    #: significance level is :attr:`DiagnosisSettings.p_value` over it with
    #: :attr:`DiagnosisSettings.multiple_testing`.
    family: int = 1
    #: The friction-law candidates of the round whose own fits explain most of the marks of
    #: the friction's speed dependence that the model before misses, with the share of
    #: those marks' χ² each removes (:func:`speed_mark_support`): the friction-law share
    #: rule does not hold them back (:attr:`DiagnosisSettings.friction_model_share`).
    mark_supported: Mapping[str, float] = field(default_factory=dict)

    @property
    def p_level(self) -> float:
        """The level a candidate's bootstrap p is judged at (Bonferroni over
        :attr:`family` with :attr:`DiagnosisSettings.multiple_testing`)."""
        if self.st.multiple_testing:
            return self.st.p_value / max(self.family, 1)
        return self.st.p_value

    def problem(
        self,
        params: Sequence[tuple[str, Param]],
        build: Callable[[Sequence[float]], System],
        experiments: Sequence[Experiment],
    ) -> FitProblem:
        return FitProblem(
            params,
            build,
            experiments,
            self.st.threads,
            self.adapt,
            self.cache,
            self.command_weights_m_per_v,
            self.level_directions,
        )

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
            s = self.model_before({n: v for (n, _), v in zip(self.free, values[:nf], strict=True)})
            return apply_extra(s, values[nf:])

        return build

    def model_before(self, free_values: Mapping[str, float]) -> System:
        """The model before a candidate (the nominal model with the effects selected so
        far) at the free nominal parameters ``free_values`` (those missing: the first
        fold's warm values)."""
        values = {**(self.warm[0] if self.warm else {}), **free_values}
        s = self.set_free(self.nominal, values)
        for cand, vals in self.selected_effects:
            s = cand.apply(s, vals)
        return s

    def best_start_setting(
        self, base: System, cand: Candidate, warm_only: bool = False
    ) -> tuple[int, ...]:
        """The setting of a discrete candidate whose model at the start of its fits (each
        fold's warm free values, and the manifest's values unless ``warm_only``) has the
        smallest training gap, summed over folds, as a one-element tuple; all its settings
        when every start fails to simulate (their fits then report why). All the settings'
        starts of a fold are simulated as one batch."""
        cost = np.zeros(len(cand.discrete))
        prior = {n: p.initial for n, p in self.free}
        for i, (train, _) in enumerate(self.folds):
            warm = self.warm[i] if i < len(self.warm) else prior
            starts = [warm] if warm == prior or warm_only else [warm, prior]
            systems = [
                self.builder(base, _at_setting(cand, k))([st[n] for n, _ in self.free])
                for k in cand.discrete
                for st in starts
            ]
            # Only its batch evaluation is used: the systems are built above.
            prob = self.problem(self.free, lambda v: base, train)
            ms = [
                math.inf if r is None else rms_of(r) ** 2 for r in prob.residuals_or_none(systems)
            ]
            cost += np.min(np.reshape(ms, (len(cand.discrete), len(starts))), axis=1)
        if not np.isfinite(cost).any():
            return cand.discrete
        return (cand.discrete[int(np.argmin(cost))],)

    def _fit_held(
        self,
        base: System,
        params: Sequence[tuple[str, Param]],
        apply_extra: Callable[[System, Sequence[float]], System],
        warm: Mapping[str, float],
        train: Sequence[Experiment],
        seed: int,
        scan_points: int | None,
        screen_starts: int,
        scan_starts: int,
        scan_only: Sequence[str] = (),
    ) -> tuple[Fit, FitProblem]:
        """A screening fit of ``params`` alone, the free nominal parameters held at their
        ``warm`` values: the same scan and starts over ``params`` as a screening fit with
        the free parameters too (whose scan draws ``params`` only, at the same points), but
        each finite-difference Jacobian costs ``len(params) + 1`` evaluations instead of
        ``len(free) + len(params) + 1``. The fit's values list the held parameters first
        (as a fit of all of them would, without standard errors: they were not fitted);
        its covariance is zero in their rows and columns."""
        held = {n: warm.get(n, p.initial) for n, p in self.free}
        full = self.builder(base, apply_extra)
        fixed = list(held.values())

        def build(values: Sequence[float]) -> System:
            return full([*fixed, *values])

        prob = self.problem(list(params), build, train)
        step = (
            self._nominal_step(base, fixed, train)
            if self.st.screen_moves_nominal and self.free
            else None
        )
        if step is not None:
            prob.projection = step.basis
        k = len(params)
        f = prob.fit(
            screen_starts,
            self.st,
            seed,
            scan=(scan_points or min(self.st.scan_points * k, self.st.scan_points_max))
            if params
            else 0,
            scan_starts=scan_starts,
            scan_only=_scan_flags([n for n, _ in params], scan_only),
        )
        nf = len(held)
        cov = np.zeros((0, 0))
        if f.unit_covariance.shape == (k, k):
            cov = np.zeros((nf + k, nf + k))
            cov[nf:, nf:] = f.unit_covariance
        f = dataclasses.replace(f, values=held | f.values, unit_covariance=cov)
        if step is not None:
            prob.projection = None
            f = self._stepped(f, step, full, prob)
        return f, prob

    def _nominal_step(
        self, base: System, fixed: Sequence[float], train: Sequence[Experiment]
    ) -> NominalStep | None:
        """The Jacobian of the model before's scaled training residual (:class:`FitProblem`)
        in the free nominal parameters' normalised coordinates at ``fixed`` (forward
        differences of :attr:`DiagnosisSettings.diff_step`, backward at an upper bound), as
        its thin singular value decomposition; None when a simulation fails. Every candidate
        of a round asks for the same simulations, which the cache keeps."""
        prob = self.problem(self.free, self.builder(base, lambda s, v: s), train)
        prob.scale_m = base.encoder.count_m
        u0 = np.array([p.to_unit(v) for (_, p), v in zip(self.free, fixed, strict=True)])
        h = self.st.diff_step
        steps = np.where(u0 + h <= 1.0, h, -h)
        points = [u0] + [u0 + d * np.eye(len(u0))[i] for i, d in enumerate(steps)]
        try:
            systems = [
                prob.build([p.from_unit(float(x)) for (_, p), x in zip(self.free, u, strict=True)])
                for u in points
            ]
        except ValueError:
            return None
        res = prob.residuals_or_none(systems)
        if any(r is None for r in res):
            return None
        vecs = [prob._scaled(r) for r in res if r is not None]
        jac = np.column_stack([(v - vecs[0]) / d for v, d in zip(vecs[1:], steps, strict=True)])
        u, sv, vt = np.linalg.svd(jac, full_matrices=False)
        if not sv.size or sv[0] <= 0.0:
            return None
        keep = sv > NOMINAL_STEP_RCOND * sv[0]
        return NominalStep(unit=u0, basis=u[:, keep], singular=sv[keep], right=vt[keep].T)

    def _stepped(
        self,
        f: Fit,
        step: NominalStep,
        full: Callable[[Sequence[float]], System],
        prob: FitProblem,
    ) -> Fit:
        """``f`` (a held screening fit) with the free nominal parameters moved by the
        Gauss–Newton step that the variable projection assumed (the least-squares solution
        of the Jacobian against the training residual at ``f``, clipped to the bounds), when
        the step lowers the training gap; else ``f`` with its training gap recomputed
        without the projection. Its ``train_rms_m`` is the gap of the model it returns."""
        own = [f.values[n] for n, _ in prob.params]
        before = prob.residuals_or_none([f.system])[0]
        if before is None:
            return f
        r = prob._scaled(before)
        delta = -step.right @ ((step.basis.T @ r) / step.singular)
        moved_unit = np.clip(step.unit + delta, 0.0, 1.0)
        moved = [p.from_unit(float(x)) for (_, p), x in zip(self.free, moved_unit, strict=True)]
        kept = dataclasses.replace(f, train_rms_m=rms_of(before))
        try:
            system = full([*moved, *own])
        except ValueError:
            return kept
        after = prob.residuals_or_none([system])[0]
        if after is None or rms_of(after) >= rms_of(before):
            return kept
        values = {n: v for (n, _), v in zip(self.free, moved, strict=True)} | {
            n: f.values[n] for n, _ in prob.params
        }
        return dataclasses.replace(f, values=values, train_rms_m=rms_of(after), system=system)

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
        hold: bool = False,
        local: bool = False,
        scan_only: Sequence[str] = (),
    ) -> tuple[list[Fit], FloatArray, list[list[FloatArray]], list[float | None], FloatArray]:
        """Fit on each fold's training experiments; mean-square gap on its validation ones
        (concatenated over folds), the validation residuals per fold, the mean-square
        command residual of each validation experiment (None without a measured command, or
        where the command is part of the gap),
        and each validation move's share of its experiment's mean square (:func:`move_units`;
        they sum to the experiment's). With ``hold`` (screening, after the calibration) the
        free nominal parameters stay at each fold's warm values and only ``params`` are
        fitted (:attr:`DiagnosisSettings.screen_holds_nominal`). With ``local``, one local
        fit per fold from the parameters' initial values (each fold's warm free values and
        the params' own): no scan, no other start."""
        fits, ms, residuals = [], [], []
        units: list[float] = []
        command: list[float | None] = []
        for i, (train, validate) in enumerate(self.folds):
            warm = self.warm[i] if i < len(self.warm) else {}
            free = [
                (n, dataclasses.replace(p, initial=warm[n]) if n in warm else p)
                for n, p in self.free
            ]
            if local:
                prob = self.problem(free + list(params), self.builder(base, apply_extra), train)
                f = prob.fit(1, self.st, seed)
            elif hold and warm:
                f, prob = self._fit_held(
                    base,
                    params,
                    apply_extra,
                    warm,
                    train,
                    seed,
                    scan_points,
                    screen_starts,
                    scan_starts,
                    scan_only,
                )
            else:
                prob = self.problem(free + list(params), self.builder(base, apply_extra), train)
                # Two starts at least: the warm values, and the manifest's (prior) values.
                prior = [p.initial for _, p in self.free] + [p.initial for _, p in params]
                # Screening uses the warm start only, except for candidates without
                # continuous parameters (delays), whose changes can move the free parameters
                # far: they also get the prior start.
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
                        scan_points
                        or min(self.st.scan_points * len(params), self.st.scan_points_max)
                    )
                    if params
                    else (0 if warm else self.st.scan_points_nominal),
                    scan_starts=scan_starts,
                    scan_only=_scan_flags([n for n, _ in free + list(params)], scan_only),
                )
            res, val_command = prob.residuals_and_commands(f.system, validate)
            fits.append(f)
            residuals.append(res)
            ms += [float(np.mean(r**2)) for r in res]
            for e, r in zip(validate, res, strict=True):
                w = self.weights.get(e.name, 1.0)
                units += [w * u for u in channel_units(r, len(e.time_s), move_units(e.reference_m))]
            command += val_command
        return fits, np.array(ms), residuals, command, np.array(units)


@single_threaded_blas()
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
    executor: Executor | Any | None = None,
) -> dict[str, Any]:
    """Run the diagnosis over train/validate folds. Returns a dict with ``nominal`` (Fit of
    the first fold), ``nominal_validation_ms``, ``floor_rms_m``, ``rounds`` (lists of
    CandidateResult, best first), ``selected`` (names), ``final`` (Fit of the first fold),
    ``final_validation_ms``, ``skipped`` (name → reason), ``refit_control`` (the rounds in
    which refitting the model before from a candidate's free values improved it),
    ``timing_s``, ``phases`` (a :class:`~.settings.PhaseClock`: the time and simulations
    per phase and round), ``simulations`` (``simulated``: simulations run, None without the
    cache; ``reused``: looked up in the :class:`SimulationCache`) and ``cache`` (that
    cache, or None: the report's simulations of the same fits look it up).

    ``executor`` (a :class:`concurrent.futures.Executor` or a ``dask.distributed.Client``;
    anything with ``submit``): the candidates' fits of each round (screening and
    refinement) run on it as tasks instead of on ``parallel_candidates`` local threads
    (:func:`_concurrently`; needs ``cloudpickle``). The results are the same whatever
    runs them; ``simulations`` then counts this process's simulations only (each task
    has its own cache)."""
    st = settings or DiagnosisSettings()
    t_start = time.perf_counter()
    executor_arg(executor)
    if not st.simulation_cache_mb >= 0.0:
        raise ValueError(
            f"DiagnosisSettings.simulation_cache_mb = {st.simulation_cache_mb!r}: must be ≥ 0 "
            "(MB of simulations kept for reuse; 0 turns the reuse off)"
        )
    ranked = rank_key(st.ranking)  # checks the setting before any work
    if isinstance(st.cross_judge_folds, bool) or not isinstance(st.cross_judge_folds, int):
        raise ValueError(
            f"DiagnosisSettings.cross_judge_folds = {st.cross_judge_folds!r}: must be an "
            "integer (folds of the cross-judging, at least 2; 0 or 1 turns it off)"
        )
    if (
        isinstance(st.jacobian_refresh, bool)
        or not isinstance(st.jacobian_refresh, int)
        or st.jacobian_refresh < 1
    ):
        raise ValueError(
            f"DiagnosisSettings.jacobian_refresh = {st.jacobian_refresh!r}: must be an integer "
            "≥ 1 (accepted steps between a fit's difference Jacobians; 1 takes one at every "
            "step)"
        )
    if not 0.0 <= st.friction_model_share <= 1.0:
        raise ValueError(
            f"DiagnosisSettings.friction_model_share = {st.friction_model_share!r}: must be "
            "in [0, 1] (share of the validation gap's mean square a friction law must explain; "
            "0 turns the rule off)"
        )
    if not 0.0 <= st.speed_mark_share <= 1.0:
        raise ValueError(
            f"DiagnosisSettings.speed_mark_share = {st.speed_mark_share!r}: must be in [0, 1] "
            "(share of the missed speed marks' χ² a candidate must remove; 0 turns the rule "
            "off)"
        )
    if not st.lag_refit_max_gap_ratio >= 1.0:
        raise ValueError(
            f"DiagnosisSettings.lag_refit_max_gap_ratio = {st.lag_refit_max_gap_ratio!r}: "
            "must be ≥ 1 (screened gap over the model before's beyond which a lag-family "
            "candidate is not refitted; inf refits every one)"
        )
    significance_mode(st.significance)
    if not folds or any(len(v) == 0 for _, v in folds):
        raise ValueError("the diagnosis needs at least one validation experiment per fold")
    every = {e.name: e for tr, va in folds for e in list(tr) + list(va)}
    floor, floors = floors_m(list(every.values()), nominal.encoder.count_m)
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
    cache = ctx.cache
    clock = PhaseClock((lambda: cache.misses) if cache is not None else None)
    # The marks of the traces (limit cycles, rest and ramp commands, breakaway) judge the
    # candidates of a tie that the validation gap cannot break (pick_winner).
    judge = SignatureJudge(
        list(every.values()),
        ctx.adapt,
        nominal.encoder.count_m,
        nominal.sample_period_s,
        ctx.cache,
        st.threads,
    )
    signature_distances: list[dict[str, float]] = []
    signature_marks: list[list[str]] = []
    # Per round that refined candidates beyond the usual refits: why, and which.
    extra_refits: list[dict[str, Any]] = []
    # Per round whose friction laws put right the speed marks the model before misses.
    mark_support: list[dict[str, Any]] = []
    # Per round whose pick, judged on every experiment, was named on the measured gap over
    # every experiment where its own fit left the validation experiments' measured gap.
    measured_on_every: list[dict[str, Any]] = []

    def signature_chi_squares(tied: Sequence[CandidateResult]) -> list[tuple[float, int]]:
        # Judged on the marks the tied effects make: each tied model against itself with
        # its effect taken out (its own refit of the free nominal parameters kept).
        bare = [ctx.model_before(_free_values(r.fit, free)) for r in tied]
        out, marks = judge.tie_chi_squares([r.fit.system for r in tied], bare)
        # The round's record is its last judgement: the one whose pick stands.
        signature_distances[-1] = {r.effect: chi2 for r, (chi2, _) in zip(tied, out, strict=True)}
        signature_marks[-1] = marks
        return out

    print_progress(
        f"diagnosis: calibrating the nominal model ({len(free)} free parameters, "
        f"{len(folds)} fold(s))",
        progress,
    )
    nominal_fits, base_ms, _, base_cmd, base_units = ctx.fit_and_validate(
        nominal, (), lambda s, v: s, st.n_starts_nominal, st.seed
    )
    ctx.warm[:] = [_free_values(f, free) for f in nominal_fits]
    cmd_weights = command_weights(
        list(every.values()),
        {n: ctx.adapt(nominal, e) for n, e in every.items()},
        floors,
        nominal.encoder.count_m,
        st,
    )
    if cmd_weights:
        # The command joins the gap: every fit and judgement from here on uses both
        # channels, each in units of its own noise floor. The nominal model is calibrated
        # again on both, from its calibration on the position.
        ctx = dataclasses.replace(ctx, command_weights_m_per_v=cmd_weights)
        w = sorted(cmd_weights.values())
        nominal_fits, base_ms, base_cmd, base_units = _calibrate_again(
            ctx,
            f"diagnosis: the measured command joins the gap in {len(w)} experiment(s) "
            f"(weight {w[len(w) // 2]:.3g} m/V, median: the position's noise floor over the "
            "command's); calibrating again on both",
            progress,
        )
    # How far a run-to-run friction level change moves each experiment (the advice on
    # repeats, and the weights of the samples with a given scatter).
    cal = nominal_fits[0].system
    sens = level_sensitivities(
        list(every.values()),
        {n: ctx.adapt(cal, e) for n, e in every.items()},
        threads=st.threads,
        cache=ctx.cache,
    )
    scatter: LevelScatter | None = None
    if st.level_scatter > 0.0:
        # Run-to-run friction scatter: each experiment's gap allows for one level draw of
        # its own (what a level within the scatter does to a long saturated slew no longer
        # decides); the nominal model is calibrated again.
        scatter = level_scatter_directions(
            list(every.values()),
            sens,
            floors,
            ctx.command_weights_m_per_v,
            nominal.encoder.count_m,
            st.level_scatter,
        )
        if scatter.directions:
            ctx = dataclasses.replace(ctx, level_directions=scatter.directions)
            nominal_fits, base_ms, base_cmd, base_units = _calibrate_again(
                ctx,
                f"diagnosis: run-to-run friction scatter {st.level_scatter:.3g} (relative "
                f"level) allowed for in the gaps of {len(scatter.directions)} experiment(s); "
                "calibrating again",
                progress,
            )
    clock.lap("calibration")
    selected: list[str] = []
    rounds: list[list[CandidateResult]] = []
    # Per round with :attr:`DiagnosisSettings.cross_judge_folds`: its refitted candidates
    # judged on every experiment (:func:`_cross_judge`), best first.
    cross_judged: list[list[CandidateResult]] = []
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
        # The round judges these candidates together (the significance level's family).
        ctx = dataclasses.replace(ctx, family=len(cand_now), mark_supported={})
        results: list[CandidateResult] = []

        now = (current, current_ms, current_cmd, current_units)
        for i, cand, r, exc, seconds in _concurrently(
            list(enumerate(cand_now)), now, ctx, screen=True, executor=executor
        ):
            if r is None:
                # An invalid combination with the effects already selected, or a
                # simulation failing at the start values: reported, not fatal.
                skipped[cand.name] = f"round {rnd + 1}: could not be fitted: {exc}"
                print_progress(f"  round {rnd + 1} {cand.name}: not fitted ({exc})", progress)
                continue
            results.append(r)
            print_progress(
                f"  round {rnd + 1} [{i + 1}/{len(cand_now)}] {cand.name:26s} "
                f"validation {r.validation_rms_m * 1e9:9.1f} nm  shrink {r.shrink:+.1%}"
                f"{'  significant' if r.significant else ''}"
                f"  ({seconds:.1f} s)",
                progress,
            )
        results.sort(key=ranked)
        clock.lap("screening", rnd + 1)
        # Refine the best few with all starts (warm, the manifest's prior, Latin
        # hypercube), then rank again.
        by_name = {c.name: (i, c) for i, c in enumerate(cand_now)}

        bent = sorted({b["parameter"] for f in current_fits for b in at_bounds(f, free)})
        missed = (
            _missed_marks(judge, current_fits[0].system)
            if st.refine_on_missed_marks and current_fits
            else []
        )
        usual = refine_names(results, st)
        names_top = refine_names(results, st, lag_family=bool(bent), missed_marks=missed)
        more = names_top[len(usual) :]
        due = extra_refit_effects(st, bool(bent), missed)
        hopeless = [n for n in hopeless_lag_refits(results, st) if n not in usual and n in due]
        if more or hopeless:
            extra_refits.append(
                {
                    "round": rnd + 1,
                    "at_bounds": bent,
                    "missed_marks": missed,
                    "refined": more,
                    "not_refined": hopeless,
                }
            )
            why = [f"{', '.join(bent)} at a bound"] if bent else []
            why += [f"marks missed ({', '.join(missed)})"] if missed else []
            print_progress(
                f"  round {rnd + 1}: the model before has {' and '.join(why)}: "
                f"refining the effects that make them too ({', '.join(more) or 'none'})"
                + (
                    f"; not {', '.join(hopeless)}: screened at more than "
                    f"{st.lag_refit_max_gap_ratio:g}× the gap before"
                    if hopeless
                    else ""
                ),
                progress,
            )
        top = [by_name[name] for name in names_top]
        # With the nominal held in screening, the results not refitted here hold the
        # model before's free values (:attr:`DiagnosisSettings.screen_holds_nominal`).
        held = {r.effect for r in results} if st.screen_holds_nominal else set()
        _refine(top, now, ctx, results, held, skipped, rnd, progress, executor)
        if st.friction_model_share > 0.0 and st.speed_mark_share > 0.0 and current_fits:
            support = speed_mark_support(
                judge,
                current_fits[0].system,
                [r for r in results if r.effect in FRICTION_MODELS and r.effect not in held],
                st.speed_mark_share,
            )
            if support:
                mark_support.append({"round": rnd + 1, "laws": dict(support)})
                ctx = dataclasses.replace(ctx, mark_supported=support)
                results = [
                    _rejudged(ctx, r, current_ms, current_cmd, current_units)
                    if r.effect in support
                    else r
                    for r in results
                ]
                print_progress(
                    f"  round {rnd + 1}: "
                    + ", ".join(f"{n} explains {v:.0%}" for n, v in support.items())
                    + " of the ramp marks' χ² the model before misses",
                    progress,
                )
        results = _judged_holm(ctx, results, current_ms, current_cmd, current_units)
        results.sort(key=ranked)
        clock.lap("refinement", rnd + 1)
        # Refitting alone: a candidate's fit moves the free nominal parameters too, and
        # may have found a better optimum of the model *without* the effect. Refit the
        # model before from each significant candidate's free values; a better
        # training fit that predicts the validation experiments no worse becomes the
        # baseline, and every candidate is judged again.
        better, records = _refit_control(
            ctx,
            current,
            [r for r in results if r.effect not in held],
            current_fits,
            current_ms,
            rnd,
            progress,
        )
        refits += records
        if better is not None:
            current_fits, current_ms, current_cmd, current_units = better
            ctx.warm[:] = [_free_values(f, free) for f in current_fits]
            if rnd == 0:
                nominal_fits, base_ms = current_fits, current_ms
            # Judged again against the new baseline; what does not depend on it (the
            # Occam factor, the units) is carried over.
            results = [_rejudged(ctx, r, current_ms, current_cmd, current_units) for r in results]
            results.sort(key=ranked)
        results = _judged_holm(ctx, results, current_ms, current_cmd, current_units)
        clock.lap("refit control", rnd + 1)
        rounds.append(results)
        if rnd == 0:
            pool_names = [r.effect for r in results]
        signature_distances.append({})
        signature_marks.append([])
        cross = st.cross_judge_folds > 1 and len(ctx.folds) == 1
        # Picks the measured-gap rule turned down this round, with the reason
        # (:attr:`DiagnosisSettings.measured_shrink_rule`): they stay not significant
        # whatever a later judging of the round says, and the round picks again.
        unmeasured: dict[str, str] = {}
        # The measured gap of the model before, once the round's first pick needs it; and
        # where the round is judged on every experiment, that judging's terms (its folds,
        # the model before refitted on each) and the measured gap of its model before over
        # all the experiments.
        measured_before: float | None = None
        every_terms: _EveryTerms | None = None
        measured_every_before: float | None = None
        own: dict[str, CandidateResult] = {}
        on_judged = False
        while True:
            if not on_judged:
                results[:] = turned_down(results, unmeasured)
                best = pick_winner(results, st, signature_chi_squares, st.signature_margin)
                while best is not None and best.effect in held:
                    # A selected effect is fitted with the free parameters too: a winner
                    # known from its held screening only is refitted from all starts, and
                    # the round picks again.
                    now = (current, current_ms, current_cmd, current_units)
                    _refine(
                        [by_name[best.effect]],
                        now,
                        ctx,
                        results,
                        held,
                        skipped,
                        rnd,
                        progress,
                        executor,
                    )
                    held.discard(best.effect)
                    again = _judged_holm(ctx, results, current_ms, current_cmd, current_units)
                    results[:] = turned_down(again, unmeasured)
                    results.sort(key=ranked)
                    best = pick_winner(results, st, signature_chi_squares, st.signature_margin)
                clock.lap("selection", rnd + 1)
            if cross and not on_judged:
                # Judged again on every experiment: the round picks among its refitted
                # candidates (the winner above among them) by these results, and selects
                # that candidate's fit above.
                pool = [(by_name[r.effect][1], r) for r in results if r.effect not in held]
                n_all = len(ctx.folds[0][0]) + len(ctx.folds[0][1])
                print_progress(
                    f"  round {rnd + 1}: judging the {len(pool)} refitted candidates again on "
                    f"all {n_all} experiments "
                    f"({len(cross_judge_split(n_all, st.cross_judge_folds))} folds)",
                    progress,
                )
                judged, every_terms = (
                    _cross_judge(ctx, current, current_fits, pool) if pool else ([], None)
                )
                own.update({r.effect: r for r in results})
                # The selection carries the round's own fit (the training experiments): an
                # effect whose own fit does not differ from none, or widens the pooled
                # validation gap, is not named on the folds' refits, which saw the
                # validation experiments too.
                cross_judged.append(without_unsupported(judged, own, st.max_pooled_widening))
                # The cross-judged pick stands: a tie of the validation round before it no
                # longer counts.
                signature_distances[-1], signature_marks[-1] = {}, []
                on_judged = True
            if on_judged:
                cross_judged[-1] = turned_down(cross_judged[-1], unmeasured)
                best = _cross_judged_pick(
                    cross_judged[-1], results, own, signature_chi_squares, st, rnd, progress
                )
                clock.lap("judged on every experiment", rnd + 1)
            # The effect named must shrink the gap as the report gives it (measured, pooled).
            if best is None or not st.measured_shrink_rule:
                break
            if measured_before is None:
                measured_before = _measured_rms(ctx, current_fits)
            reason, own_shrink = _measured_shrink_reason(ctx, measured_before, best, st)
            if reason is not None and on_judged and every_terms is not None and own_shrink >= 0.0:
                # Picked on every experiment: its folds' fits may shrink the gap as measured
                # over all of them where its own fit leaves the validation experiments' gap
                # (one large step, say, whose run-to-run level the judged gaps discount). An
                # own fit that widens that gap at all stays turned down: the model the
                # report carries never widens the headline's gap by the effect it names.
                if measured_every_before is None:
                    measured_every_before = _measured_rms(every_terms.ctx, every_terms.base)
                on_every, passes = _measured_on_every(
                    every_terms,
                    measured_every_before,
                    next(r for r in cross_judged[-1] if r.effect == best.effect),
                    st,
                )
                if passes:
                    measured_on_every.append(
                        {
                            "round": rnd + 1,
                            "effect": best.effect,
                            "every_experiment": on_every,
                            "validation": reason,
                        }
                    )
                    print_progress(
                        f"  round {rnd + 1}: {best.effect} named: {on_every}; on the "
                        f"validation experiments {reason}",
                        progress,
                    )
                    break
                reason = f"{reason}; {on_every}"
            if reason is None:
                break
            print_progress(f"  round {rnd + 1}: {best.effect} turned down: {reason}", progress)
            unmeasured[best.effect] = reason
            results[:] = turned_down(results, unmeasured)
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
        "command_weights_m_per_v": dict(ctx.command_weights_m_per_v),
        "level_directions": dict(ctx.level_directions),
        "level_scatter": None if scatter is None else scatter.to_dict(),
        # A 1 % friction level change in units of each experiment's noise floor.
        "level_floors": level_floors(sens, floors),
        "nominal": nominal_fits[0],
        "nominal_fits": nominal_fits,
        "nominal_validation_ms": base_ms,
        "floor_rms_m": floor,
        "experiment_floors_m": floors,
        "kind_floors": st.kind_floors,
        "rounds": rounds,
        "cross_judged": cross_judged,
        "selected": selected,
        "selected_effects": list(ctx.selected_effects),
        "final": current_fits[0],
        "final_fits": current_fits,
        "final_validation_ms": current_ms,
        "skipped": skipped,
        "refit_control": refits,
        "timing_s": time.perf_counter() - t_start,
        # Where the time went, per phase and round (the caller laps its own phases on it).
        "phases": clock,
        "signature_judge": judge,
        # Per round, the signature χ² of each candidate its deciding tie put before the
        # judge (the last judgement: after any refit, the cross-judged one where there is).
        "signature_distances": signature_distances,
        # Per round, the marks that judgement judged on (the features the tied effects move).
        "signature_marks": signature_marks,
        "extra_refits": extra_refits,
        "speed_mark_support": mark_support,
        "measured_on_every": measured_on_every,
        "cache": ctx.cache,
        "simulations": {
            "simulated": None if ctx.cache is None else ctx.cache.misses,
            "reused": 0 if ctx.cache is None else ctx.cache.hits,
        },
    }


def _scan_flags(names: Sequence[str], scan_only: Sequence[str]) -> list[bool] | None:
    """Per parameter of a fit (``names``), whether its scan may draw it
    (:attr:`~.candidates.Candidate.scan_only`); None when every parameter may."""
    if not scan_only:
        return None
    return [n in scan_only for n in names]


def _cross_judged_pick(
    judged: Sequence[CandidateResult],
    results: Sequence[CandidateResult],
    own: Mapping[str, CandidateResult],
    signature_chi_squares: Callable[[Sequence[CandidateResult]], list[tuple[float, int]]],
    st: DiagnosisSettings,
    rnd: int,
    progress: bool,
) -> CandidateResult | None:
    """The round's result (of ``results``) of the candidate a round picks on its results
    judged on every experiment (``judged``), or None. A tie among them is broken on the
    signatures of the round's own fits (``own``: all starts, the training experiments; the
    fits the report's signature table shows), not on a fold's local refit: that fold leaves
    out a third of the experiments, possibly those that show the effect, so its fit may have
    drifted away from it."""

    def on_own_fits(tied: Sequence[CandidateResult]) -> list[tuple[float, int]]:
        return signature_chi_squares([own.get(r.effect, r) for r in tied])

    pick = pick_winner(judged, st, on_own_fits, st.signature_margin)
    if pick is None:
        return None
    print_progress(
        f"  round {rnd + 1}: {pick.effect} judged on all experiments: geometric "
        f"shrink {pick.geometric_shrink:.1%}, p = {pick.p_value:.3f}",
        progress,
    )
    return next(r for r in results if r.effect == pick.effect)


def _measured_rms(ctx: _Ctx, fits: Sequence[Fit]) -> float:
    """The pooled RMS of the validation gap of a model (``fits``: one per fold, each judged
    on its fold's validation experiments) as measured: the reading alone, without the
    command channel and without the level-scatter discount (the measure of the report's
    headline)."""
    squares, n = 0.0, 0
    for (_, validate), f in zip(ctx.folds, fits, strict=True):
        system = f.system

        def build(_values: Sequence[float], s: System = system) -> System:
            return s

        prob = FitProblem([], build, validate, ctx.st.threads, ctx.adapt, ctx.cache)
        for r in prob.residuals(system, validate):
            squares += float(np.sum(r**2))
            n += r.size
    return math.sqrt(squares / n) if n else 0.0


def _measured_shrink(
    ctx: _Ctx, rms0: float, pick: CandidateResult, st: DiagnosisSettings
) -> tuple[float, float, float]:
    """The measured pooled gap of ``pick``'s fits (one per fold of ``ctx``, each on its
    fold's validation experiments, :func:`_measured_rms`), its shrink of ``rms0`` (the model
    before's, on the same folds) and the complexity penalty it must exceed
    (:attr:`DiagnosisSettings.measured_shrink_rule`)."""
    rms1 = _measured_rms(ctx, pick.fold_fits)
    shrink = 1.0 - rms1 / rms0 if rms0 > 0.0 else 0.0
    return rms1, shrink, st.penalty(pick.k_params)


def _measured_on_every(
    terms: _EveryTerms, rms0: float, judged: CandidateResult, st: DiagnosisSettings
) -> tuple[str, bool]:
    """The measured-gap rule judged on every experiment: a sentence with the measured pooled
    gap over every experiment, each held out once, of the model before (``rms0``) and of
    ``judged`` (a pick's result in those terms), and whether it shrinks by more than the
    complexity penalty."""
    rms1, shrink, penalty = _measured_shrink(terms.ctx, rms0, judged, st)
    passes = shrink > penalty
    return (
        f"judged on every experiment, each held out once, the gap as measured goes "
        f"{rms0 * 1e9:.0f} → {rms1 * 1e9:.0f} nm, shrink {shrink:.1%} "
        f"{'>' if passes else '≤'} complexity penalty {penalty:.0%}"
    ), passes


def _measured_shrink_reason(
    ctx: _Ctx, rms0: float, pick: CandidateResult, st: DiagnosisSettings
) -> tuple[str | None, float]:
    """Why the effect of ``pick`` cannot be named (its own fits shrink ``rms0``, the
    measured pooled validation gap of the model before (:func:`_measured_rms`), by no more
    than its complexity penalty, :attr:`DiagnosisSettings.measured_shrink_rule`), or None
    when it can; and that shrink."""
    rms1, shrink, penalty = _measured_shrink(ctx, rms0, pick, st)
    if shrink > penalty:
        return None, shrink
    return (
        f"the gap as measured (the reading pooled over the validation experiments, no "
        f"level-scatter discount) goes {rms0 * 1e9:.0f} → {rms1 * 1e9:.0f} nm, shrink "
        f"{shrink:.1%} ≤ complexity penalty {penalty:.0%}: the effect does not explain the "
        "gap the report gives"
    ), shrink


def _calibrate_again(
    ctx: _Ctx, message: str, progress: bool
) -> tuple[list[Fit], FloatArray, list[float | None], FloatArray]:
    """Calibrate the nominal model again from its warm values (one local fit per fold) after
    the gap changed (the command joined it, or its samples were weighted); the warm values
    become the new fits'. Returns the fits, the validation mean squares, the validation
    command residuals and the validation moves' shares (as :meth:`_Ctx.fit_and_validate`)."""
    print_progress(message, progress)
    fits, ms, _, cmd, units = ctx.fit_and_validate(ctx.nominal, (), lambda s, v: s, 1, ctx.st.seed)
    ctx.warm[:] = [_free_values(f, ctx.free) for f in fits]
    return fits, ms, cmd, units


def command_weights(
    experiments: Sequence[Experiment],
    systems: Mapping[str, System],
    floors: Mapping[str, float],
    count_m: float,
    st: DiagnosisSettings,
) -> dict[str, float]:
    """The weight of each experiment's command gap against its position gap, m/V (by name).
    ``systems``: each experiment's model (its controller gains); ``floors``: each
    experiment's position noise floor, m (:func:`floors_m`).

    With :attr:`DiagnosisSettings.command_channel`, an experiment with a measured command
    gets the weight ``position floor / command floor`` (:func:`experiment_floors_m`,
    :func:`command_floors_v`), so that each channel counts in units of its own noise floor:
    a friction law that moves the position by a fraction of a count but the command by many
    times its floor shows. Without repeats the command's floor is the position's through the
    controller's proportional gain, and the weight its inverse: the command gap counts as
    the position error that would make it. A constant command, or one clipped at the rails
    for most of the experiment (:func:`command_problems`), is left out. The experiment's gap
    then stacks both channels, and its floor is the root mean square of the two floors in
    position units, equal to the position's (each channel is at its floor together), so
    the floors stay the position's. Without a command (or a usable floor) there is no
    weight."""
    if not st.command_channel or all(e.command_v is None for e in experiments):
        return {}
    gains = {n: proportional_gain_v_per_m(s) for n, s in systems.items()}
    cmd = command_floors_v(experiments, count_m, floors, gains)
    _, unusable = command_problems(experiments, systems)
    return {n: floors[n] / f for n, f in cmd.items() if f > 0.0 and n not in unusable}


def _missed_marks(judge: SignatureJudge, system: System) -> list[str]:
    """The marks of the traces the fitted model before (``system``, the first fold's fit)
    misses by more than three standard errors (:func:`~.signatures.misses`); none when the
    traces have no mark or its simulation fails (the round's fits report such failures)."""
    if not judge.measured:
        return []
    try:
        simulated = judge.simulated(system)
    except (RuntimeError, ValueError):
        return []
    return [str(m["feature"]) for m in misses(judge.measured, simulated)]


def speed_mark_support(
    judge: SignatureJudge,
    before: System,
    results: Sequence[CandidateResult],
    share: float,
) -> dict[str, float]:
    """The candidates among ``results`` (each with its own fit; the friction laws, as the
    diagnosis calls it) that explain at least ``share`` of the χ² of the
    :data:`SPEED_MARKS` the model ``before`` misses by more than three standard errors,
    with the share each explains (by name; empty when ``before`` misses none of them or
    the traces have none).

    A friction law replaces the nominal law, and any law fitted to a model's friction
    takes up part of the law's form error, so it must explain most of the gap
    (:attr:`DiagnosisSettings.friction_model_share`). That form error lies where the
    force builds up after a reversal (presliding); a steady ramp's command is the sliding
    friction at the ramp's speed. When the calibrated model before misses those commands
    (its friction at slow and fast speeds cannot both be right) and a law's fit puts them
    right, the law explains a mark of its own, whatever share of the gap it removes.
    Nothing is simulated when the traces have no ramp command."""
    if not results or not any(m in judge.measured for m in SPEED_MARKS):
        return {}
    try:
        base = judge.simulated(before)
    except (RuntimeError, ValueError):
        return {}
    missed = {str(m["feature"]) for m in misses(judge.measured, base)}
    measured = {m: judge.measured[m] for m in SPEED_MARKS if m in missed}
    if not measured:
        return {}
    chi0 = chi_square(measured, base)[0]
    out: dict[str, float] = {}
    for r in results:
        try:
            chi1, n = chi_square(measured, judge.simulated(r.fit.system))
        except (RuntimeError, ValueError):
            continue  # its simulation failed: no support
        explained = 1.0 - chi1 / chi0
        if n == len(measured) and explained >= share:
            out[r.effect] = explained
    return out


def mark_effects(mark: str) -> tuple[str, ...]:
    """The candidates that make a mark of the traces (a feature of
    :mod:`~nanostage.diagnosis.signatures`) which the nominal model's friction does not:
    for :data:`BIAS_MARKS` the :data:`BIAS_ALIASES`, for :data:`BREAKAWAY_MARKS` the
    dwell-dependent friction, for every other mark (the limit cycle in holds, the ramps'
    level and slope, the split of the rest command, the lost motion at reversals) the
    :data:`LAG_FAMILY`: a lag or a play makes a limit cycle and lost motion itself, and a
    calibration bent to stand in for one misses the friction level on ramps and at rest
    (a lag cannot move a bias or a breakaway's dwell dependence, so those marks do not
    call for it)."""
    if mark in BIAS_MARKS:
        return BIAS_ALIASES
    if mark in BREAKAWAY_MARKS:
        return ("dwell_static_friction",)
    return LAG_FAMILY


def extra_refit_effects(
    st: DiagnosisSettings, at_bounds: bool, missed_marks: Sequence[str]
) -> list[str]:
    """The candidates a round refits beyond the usual refits, in no particular order: the
    :data:`LAG_FAMILY` when the model before has a free parameter at its bound
    (:attr:`DiagnosisSettings.refine_lag_family_at_bounds`), and the candidates that make
    each mark it misses (:func:`mark_effects`,
    :attr:`DiagnosisSettings.refine_on_missed_marks`)."""
    out = list(LAG_FAMILY) if at_bounds and st.refine_lag_family_at_bounds else []
    if st.refine_on_missed_marks:
        for mark in missed_marks:
            out += [e for e in mark_effects(mark) if e not in out]
    return out


def refine_names(
    results: Sequence[CandidateResult],
    st: DiagnosisSettings,
    lag_family: bool = False,
    missed_marks: Sequence[str] = (),
) -> list[str]:
    """The candidates of a round refitted from all starts, from its screened results (best
    first): the best :attr:`DiagnosisSettings.refine_top`, and with
    :attr:`DiagnosisSettings.refine_best_friction_model` the best-screened friction-model
    candidate outside them (one at most); with
    :attr:`DiagnosisSettings.refine_bias_aliases`, the other member of
    :data:`BIAS_ALIASES` when one of them is refined; then the candidates of
    :func:`extra_refit_effects` (``lag_family``: the model before has a free parameter at
    its bound; ``missed_marks``: the marks of the traces it misses) among them, in
    screening order, but for the lag-family members whose screened validation gap is more
    than :attr:`DiagnosisSettings.lag_refit_max_gap_ratio` times the model before's
    (:func:`hopeless_lag_refits`)."""
    names = [r.effect for r in results[: st.refine_top]]
    if st.refine_best_friction_model:
        rest = (r.effect for r in results[st.refine_top :] if r.effect in FRICTION_MODELS)
        best = next(rest, None)
        if best is not None:
            names.append(best)
    if st.refine_bias_aliases and any(n in BIAS_ALIASES for n in names):
        names += [r.effect for r in results if r.effect in BIAS_ALIASES and r.effect not in names]
    due = set(extra_refit_effects(st, lag_family, missed_marks))
    if due:
        skip = set(hopeless_lag_refits(results, st))
        names += [
            r.effect
            for r in results
            if r.effect in due and r.effect not in names and r.effect not in skip
        ]
    return names


def hopeless_lag_refits(results: Sequence[CandidateResult], st: DiagnosisSettings) -> list[str]:
    """The lag-family candidates outside the usual refits whose screened pooled validation
    gap is more than :attr:`DiagnosisSettings.lag_refit_max_gap_ratio` times the model
    before's (pooled shrink below ``1 − ratio``), in screening order: the lag family's extra
    refits undo a calibration bent a few tens of per cent to stand in for a lag, not a
    candidate that multiplies the gap (a one-sample delay added to a loop without one)."""
    usual = {r.effect for r in results[: st.refine_top]}
    return [
        r.effect
        for r in results
        if r.effect in LAG_FAMILY
        and r.effect not in usual
        and r.shrink < 1.0 - st.lag_refit_max_gap_ratio
    ]


def _refine(
    items: Sequence[tuple[int, Candidate]],
    now: tuple[System, FloatArray, Sequence[float | None], FloatArray | None],
    ctx: _Ctx,
    results: list[CandidateResult],
    held: set[str],
    skipped: dict[str, str],
    rnd: int,
    progress: bool,
    executor: Any,
) -> None:
    """Refit the candidates ``items`` from all starts (:func:`_judge` without ``screen``)
    against the model ``now``, each result replacing the candidate's in ``results`` (in
    place) and leaving ``held``; a candidate whose refit fails keeps its screened result
    and the reason goes to ``skipped``."""
    where = {r.effect: j for j, r in enumerate(results)}
    for _, cand, refined, exc, seconds in _concurrently(
        items, now, ctx, screen=False, executor=executor
    ):
        held.discard(cand.name)
        if refined is None:
            skipped[cand.name] = f"round {rnd + 1}: refit failed: {exc}"
            continue
        results[where[cand.name]] = refined
        print_progress(
            f"  round {rnd + 1} refit {cand.name:26s} validation "
            f"{refined.validation_rms_m * 1e9:9.1f} nm  shrink {refined.shrink:+.1%}"
            f"{'  significant' if refined.significant else ''}"
            f"  ({seconds:.1f} s)",
            progress,
        )


def _concurrently(
    items: Sequence[tuple[int, Candidate]],
    now: tuple[System, FloatArray, Sequence[float | None], FloatArray | None],
    ctx: _Ctx,
    screen: bool,
    executor: Any = None,
) -> Iterator[tuple[int, Candidate, CandidateResult | None, Exception | None, float]]:
    """:func:`_judge` of each ``(index, candidate)`` against the model ``now`` (system,
    validation mean squares, command residuals, move units), up to
    ``ctx.st.parallel_candidates`` at a time, yielded in the order given:
    ``(i, cand, result, None, seconds)``, or ``(i, cand, None, error, seconds)`` for a
    candidate that could not be fitted (``ValueError``/``RuntimeError``). The candidates'
    fits are independent (each its own problem, starts and seed), so the results do not
    depend on how many run at once: two at once overlap one fit's Python work with the
    other's simulations (which release the GIL).

    With ``executor`` (anything with ``submit``: a :class:`concurrent.futures.Executor`, a
    ``dask.distributed.Client``) every candidate is one task of :func:`_judge_task`, its
    arguments pickled once by ``cloudpickle`` (the model's closures travel by value), and
    the executor decides how many run at once. A task has its own
    :class:`SimulationCache` (the diagnosis's stays in this process): the results are the
    same, only a refit does not find its screening's simulations."""
    if executor is not None:
        yield from _on_executor(items, now, ctx, screen, executor)
        return

    def one(item: tuple[int, Candidate]) -> tuple[CandidateResult | None, Exception | None, float]:
        return _judge_timed(item[1], now, ctx, screen)

    threads = max(1, min(ctx.st.parallel_candidates, len(items)))
    with ThreadPoolExecutor(max_workers=threads) as pool:
        outcomes = pool.map(one, items) if threads > 1 else map(one, items)
        for (i, cand), (r, exc, dt) in zip(items, outcomes, strict=True):
            yield i, cand, r, exc, dt


def _judge_timed(
    cand: Candidate,
    now: tuple[System, FloatArray, Sequence[float | None], FloatArray | None],
    ctx: _Ctx,
    screen: bool,
) -> tuple[CandidateResult | None, Exception | None, float]:
    """:func:`_judge`, its error if the candidate cannot be fitted, and its seconds."""
    t0 = time.perf_counter()
    try:
        r = _judge(cand, *now, ctx, screen=screen)
    except (ValueError, RuntimeError) as exc:
        return None, exc, time.perf_counter() - t0
    return r, None, time.perf_counter() - t0


def _judge_task(
    shared: bytes, index: int, screen: bool
) -> tuple[CandidateResult | None, Exception | None, float]:
    """One candidate's :func:`_judge_timed` on an executor's worker: ``shared`` is the
    ``cloudpickle`` of ``(candidates by index, now, ctx)`` (the same bytes for every task of
    a round). Top level, so that it pickles by reference."""
    import cloudpickle

    keep_one_blas_thread()
    cands, now, ctx = cloudpickle.loads(shared)
    mb = ctx.st.simulation_cache_mb
    ctx = dataclasses.replace(ctx, cache=SimulationCache(mb * 1e6) if mb > 0 else None)
    return _judge_timed(cands[index], now, ctx, screen)


def _on_executor(
    items: Sequence[tuple[int, Candidate]],
    now: tuple[System, FloatArray, Sequence[float | None], FloatArray | None],
    ctx: _Ctx,
    screen: bool,
    executor: Any,
) -> Iterator[tuple[int, Candidate, CandidateResult | None, Exception | None, float]]:
    try:
        import cloudpickle
    except ImportError as exc:  # pragma: no cover - cloudpickle comes with dask
        raise ImportError(
            "diagnose_experiments(executor=...) pickles the candidates' fits with "
            "cloudpickle: install it (pip install 'nanostage[dask]')"
        ) from exc
    shared = cloudpickle.dumps(
        ({i: c for i, c in items}, now, dataclasses.replace(ctx, cache=None))
    )
    futures = []
    try:
        for i, _ in items:
            futures.append(executor.submit(_judge_task, shared, i, screen))
        for (i, cand), fut in zip(items, futures, strict=True):
            r, err, dt = fut.result()
            yield i, cand, r, err, dt
    except BaseException:
        # A failed task, Ctrl-C or a generator closed early: the tasks not yet started are
        # cancelled. The executor is the caller's: it is not shut down.
        for f in futures:
            f.cancel()
        raise


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


@single_threaded_blas()
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
    command_weights_m_per_v: Mapping[str, float] | None = None,
    level_directions: Mapping[str, tuple[FloatArray, float]] | None = None,
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
    the common warm start, on the experiments the folds have in common) are looked up. The
    fits use the command and allow for the level scatter as the diagnosis did
    (``command_weights_m_per_v``, ``level_directions``)."""
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
                params += _warm_params(cand, values)

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

        return FitProblem(
            params,
            build,
            training,
            settings.threads,
            adapt,
            cache,
            command_weights_m_per_v,
            level_directions,
        )

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

    pairs = _thread_map(fit_pair, jobs, settings.parallel_candidates)
    return [(judged, b, a) for (_, judged), (b, a) in zip(jobs, pairs, strict=True)]


def _thread_map(f: Callable[[Any], Any], items: Sequence[Any], parallel: int) -> list[Any]:
    """``[f(x) for x in items]``, on up to ``parallel`` threads (in this thread with one)."""
    threads = max(1, min(parallel, len(items)))
    with ThreadPoolExecutor(max_workers=threads) as pool:
        return list(pool.map(f, items) if threads > 1 else map(f, items))


def _warm_params(cand: Candidate, values: Sequence[float]) -> list[tuple[str, Param]]:
    """A continuous candidate's own parameters, named ``effect.parameter``, starting at
    ``values`` (its fitted ones)."""
    return [
        (f"{cand.name}.{q.name}", dataclasses.replace(q, initial=float(v)))
        for q, v in zip(cand.params, values, strict=True)
    ]


def cross_judge_split(
    n: int,
    k: int,
    classes: Sequence[int] | None = None,
    scales: Sequence[float] | None = None,
) -> list[list[int]]:
    """The held-out indices of each fold of :func:`_cross_judge` over ``n`` experiments;
    every experiment is held out once, and ``k`` is clipped to [2, n]. Without ``classes``
    fold ``j`` holds out ``j, j + k, j + 2k, …`` (round robin). With ``classes`` (one per
    experiment, :func:`experiment_class`) the experiments are dealt round robin class by
    class, the count running on from one class to the next: each fold holds out at most
    ``⌈m/k⌉`` of a class of ``m``, so that no fold trains on one ramp while it judges the
    other two (stratified folds). With ``scales`` too (one per experiment,
    :func:`experiment_scale`) each class is dealt largest first: its ``k`` largest are held
    out in different folds, so that every fold trains on one of the two largest of each
    kind that has two, and no fold predicts a kind's large motions from its small ones
    alone (the largest is still predicted from the next; the same order as without
    ``scales`` where they are equal)."""
    k = max(2, min(k, n))
    if classes is None:
        order = list(range(n))
    elif scales is None:
        order = sorted(range(n), key=lambda i: classes[i])
    else:
        order = sorted(range(n), key=lambda i: (classes[i], -scales[i]))
    return [sorted(order[j::k]) for j in range(k)]


def experiment_scale(reference_m: npt.ArrayLike) -> float:
    """The size of the motion an experiment asks for, for the order of
    :func:`cross_judge_split`: the largest change of its reference from one sample to the
    next, m (a step's height, a ramp's speed times the sample period, a micro-step's
    counts); 0 for a constant reference."""
    d = np.abs(np.diff(np.asarray(reference_m, dtype=np.float64)))
    return float(np.max(d)) if d.size else 0.0


def experiment_class(reference_m: npt.ArrayLike, count_m: float) -> int:
    """The coarse kind of an experiment from its reference, for stratified folds
    (:func:`cross_judge_split`): 0 with a constant-velocity ramp
    (:func:`~.objective.ramp_intervals`), 1 when every move is of at most
    :data:`~.objective.MICRO_STEP_MAX_COUNTS` counts (micro-steps: breakaway, presliding),
    2 otherwise (steps and step reversals)."""
    ref = np.asarray(reference_m, dtype=np.float64)
    if ramp_intervals(ref):
        return 0
    d = np.abs(np.diff(ref))
    return 1 if d.size and float(np.max(d)) <= MICRO_STEP_MAX_COUNTS * count_m else 2


@dataclass(frozen=True)
class _EveryTerms:
    """The terms of a round judged on every experiment (:func:`_cross_judge`): its context
    (``folds``: each experiment held out once) and the model before refitted on each fold
    (``base``)."""

    ctx: _Ctx
    base: list[Fit]


def _cross_judge(
    ctx: _Ctx,
    current: System,
    current_fits: Sequence[Fit],
    pool: Sequence[tuple[Candidate, CandidateResult]],
) -> tuple[list[CandidateResult], _EveryTerms]:
    """The candidates of ``pool`` (each with its refitted result) judged again on every
    experiment, training ones included (:attr:`DiagnosisSettings.cross_judge_folds`): for
    each fold of :func:`cross_judge_split` the model before and each candidate are refitted
    by one local fit (from the model before's fitted free values, and from the candidate's
    fitted free and own values; a delay keeps its setting) on the other experiments, and
    judged by the same rules on the held-out ones. Returns the candidates' results in these
    terms, best first by the ranking, and the terms themselves (:class:`_EveryTerms`)."""
    st = ctx.st
    train, validate = ctx.folds[0]
    exps = [*train, *validate]
    held = cross_judge_split(
        len(exps),
        st.cross_judge_folds,
        [experiment_class(e.reference_m, current.encoder.count_m) for e in exps],
        [experiment_scale(e.reference_m) for e in exps],
    )
    folds = [
        ([e for i, e in enumerate(exps) if i not in out], [exps[i] for i in out]) for out in held
    ]
    base_warm = _free_values(current_fits[0], ctx.free)
    cj = dataclasses.replace(
        ctx, folds=folds, warm=[dict(base_warm) for _ in folds], family=len(pool)
    )
    base_fits, base_ms, _, base_cmd, base_units = cj.fit_and_validate(
        current, (), lambda s, v: s, 1, st.seed, local=True
    )

    def one(item: tuple[Candidate, CandidateResult]) -> CandidateResult:
        cand, r = item
        warm = _free_values(r.fold_fits[0], ctx.free)
        c = dataclasses.replace(cj, warm=[dict(warm) for _ in folds])
        params: list[tuple[str, Param]] = []
        apply: Callable[[System, Sequence[float]], System] = cand.apply
        if cand.discrete:
            assert r.setting is not None
            apply = _at_setting(cand, r.setting)
        else:
            params = _warm_params(cand, _effect_values(cand, r))
        fits, ms, _, cmd, units = c.fit_and_validate(
            current, params, apply, 1, st.seed + r.index, local=True
        )
        v = _verdict(
            cand.name,
            fits,
            ms,
            cmd,
            r.setting,
            r.k_params,
            base_ms,
            base_cmd,
            cj,
            r.index,
            units,
            base_units,
            _null_params(cand),
        )
        return dataclasses.replace(v, log_occam=r.log_occam, units=r.units)

    out = _judged_holm(
        cj, _thread_map(one, pool, st.parallel_candidates), base_ms, base_cmd, base_units
    )
    out.sort(key=rank_key(st.ranking))
    return out, _EveryTerms(cj, list(base_fits))


def _refit_control(
    ctx: _Ctx,
    current: System,
    results: Sequence[CandidateResult],
    current_fits: Sequence[Fit],
    current_ms: FloatArray,
    rnd: int,
    progress: bool,
) -> tuple[
    tuple[list[Fit], FloatArray, list[float | None], FloatArray] | None, list[dict[str, Any]]
]:
    """The model before, refitted from the free values of each of the best
    ``refit_control_top`` significant candidates (None: all). Returns the new baseline (its
    fits, validation mean squares, command residuals and move units) or None, and the
    records for the report. A refit that fits the training data better than
    ``current_fits`` (by more than 0.1 % in mean square) becomes the baseline if it does
    not predict the validation experiments worse (:func:`judged_shrink` ≥ 0): the best in
    training of those; a better-training refit that predicts them worse is recorded
    (``adopted`` false) and not adopted, since every effect would be credited for taking
    back what that baseline lost on them."""
    st = ctx.st
    if not ctx.free or (st.refit_control_top is not None and st.refit_control_top <= 0):
        return None, []
    saved = list(ctx.warm)

    def train_ms(fits: Sequence[Fit]) -> float:
        return float(np.mean([f.train_rms_m**2 for f in fits]))

    before = train_ms(current_fits)
    best: tuple[list[Fit], FloatArray, list[float | None], FloatArray] | None = None
    # The best-training refit adopted, and the best-training one not adopted, with their
    # training mean squares.
    kept: dict[bool, dict[str, Any]] = {}
    kept_train: dict[bool, float] = {}
    try:
        for r in [r for r in results if r.significant][: st.refit_control_top]:
            ctx.warm[:] = [_free_values(f, ctx.free) for f in r.fold_fits]
            fits, ms, _, cmd, units = ctx.fit_and_validate(current, (), lambda s, v: s, 1, st.seed)
            t = train_ms(fits)
            print_progress(
                f"  round {rnd + 1} refit control from {r.effect}'s free values: training "
                f"{math.sqrt(t) * 1e9:.1f} nm (before {math.sqrt(before) * 1e9:.1f})",
                progress,
            )
            validation_shrink = judged_shrink(ctx, current_ms, ms)
            adopted = validation_shrink >= 0.0
            if t >= min(before * (1.0 - 1e-3), kept_train.get(adopted, math.inf)):
                continue
            kept_train[adopted] = t
            kept[adopted] = {
                "round": rnd + 1,
                "restarted_from": r.effect,
                "train_rms_before_m": math.sqrt(before),
                "train_rms_after_m": math.sqrt(t),
                "validation_rms_before_m": math.sqrt(float(np.mean(current_ms))),
                "validation_rms_after_m": math.sqrt(float(np.mean(ms))),
                "validation_shrink": validation_shrink,
                "adopted": adopted,
            }
            if adopted:
                best = (fits, ms, cmd, units)
    finally:
        ctx.warm[:] = saved
    if False in kept:
        print_progress(
            f"  round {rnd + 1} refit control from {kept[False]['restarted_from']}'s free "
            "values fits the training data better but predicts the validation experiments "
            f"worse (shrink {kept[False]['validation_shrink']:+.1%}): not the baseline",
            progress,
        )
    records = [kept[a] for a in (True, False) if a in kept]
    return best, records


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


def candidate_seed(name: str) -> int:
    """A candidate's seed offset (added to :attr:`DiagnosisSettings.seed` for its fits'
    starts and scans and its bootstrap), from its name alone: a candidate is fitted and
    judged alike whether a diagnosis has all candidates or only a few (where the gap is
    rugged, other draws can end in another basin: docs/diagnosis.md, *Candidates*)."""
    return zlib.crc32(name.encode("utf-8")) % 100_000


def _judge(
    cand: Candidate,
    base: System,
    base_ms: FloatArray,
    base_cmd: Sequence[float | None],
    base_units: FloatArray | None,
    ctx: _Ctx,
    screen: bool = False,
) -> CandidateResult:
    """Fit one candidate on every fold and judge it on the validation experiments
    (``screen``: one warm start only, for ranking). Its starts, scans and bootstrap are
    seeded by :func:`candidate_seed`: the same whatever other candidates the diagnosis has."""
    st = ctx.st
    index = candidate_seed(cand.name)
    extra = [(f"{cand.name}.{p.name}", p) for p in cand.params]
    setting: int | None = None
    hold = screen and st.screen_holds_nominal
    if cand.discrete:
        best: tuple[list[Fit], FloatArray, list[float | None], int, FloatArray] | None = None
        # Screening fits only the setting whose start fits the training experiments best
        # (each setting's fit costs as much as a whole continuous candidate's); refining
        # fits every setting.
        ks = ctx.best_start_setting(base, cand, warm_only=hold) if screen else cand.discrete
        for k in ks:
            fits, ms, _, cmd, units = ctx.fit_and_validate(
                base, (), _at_setting(cand, k), 1, st.seed + index, screen, hold=hold
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
            hold=hold,
            scan_only=[f"{cand.name}.{n}" for n in cand.scan_only],
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
        _null_params(cand),
    )
    return dataclasses.replace(
        result,
        log_occam=log_occam_factor(fits[0], [n for n, _ in extra], len(cand.discrete)),
        units={n: p.unit for n, p in extra},
    )


def _judged_holm(
    ctx: _Ctx,
    results: Sequence[CandidateResult],
    base_ms: FloatArray,
    base_cmd: Sequence[float | None],
    base_units: FloatArray | None,
) -> list[CandidateResult]:
    """``results`` (one family of :attr:`_Ctx.family` candidates, each judged against the
    model before's ``base_ms``, ``base_cmd``, ``base_units``) judged again at the levels of
    Holm's step-down (:func:`~.select.holm_levels`) with
    :attr:`DiagnosisSettings.multiple_testing`, a step passed only by a candidate that
    passes every other rule too. The smallest p is judged at the Bonferroni level as before
    and the step-down stops where Bonferroni's candidates end, so whether the family has
    anything significant does not change; the next ones are judged at levels that grow as
    the smaller ones pass. A candidate that explains more of the gap than the first
    significant one and misses Bonferroni's level by a little is then no longer passed over
    for it. Same order as ``results``."""
    st = ctx.st
    if not st.multiple_testing or not results:
        return list(results)
    divisors = holm_levels(
        [r.p_value for r in results],
        st.p_value,
        ctx.family,
        [r.other_rules_pass for r in results],
    )
    out: list[CandidateResult] = []
    for r, d in zip(results, divisors, strict=True):
        same = r.p_level == st.p_value / d
        out.append(r if same else _rejudged(ctx, r, base_ms, base_cmd, base_units, divisor=d))
    return out


def _rejudged(
    ctx: _Ctx,
    r: CandidateResult,
    base_ms: FloatArray,
    base_cmd: Sequence[float | None],
    base_units: FloatArray | None,
    *,
    divisor: int | None = None,
) -> CandidateResult:
    """``r`` judged again (:func:`_verdict`) against the model before's ``base_ms``,
    ``base_cmd``, ``base_units`` (``divisor``: as there); what does not depend on the
    judgement (the Occam factor, the units) is carried over."""
    v = _verdict(
        r.effect,
        r.fold_fits,
        r.validation_ms,
        r.validation_command_ms,
        r.setting,
        r.k_params,
        base_ms,
        base_cmd,
        ctx,
        r.index,
        r.validation_units,
        base_units,
        r.null_params,
        divisor=divisor,
    )
    return dataclasses.replace(v, log_occam=r.log_occam, units=r.units)


def _null_params(cand: Candidate) -> tuple[tuple[str, Param], ...]:
    """The candidate's parameters that have a null value, by their names in a fit."""
    return tuple((f"{cand.name}.{p.name}", p) for p in cand.params if p.null is not None)


def _shrink_terms(
    ctx: _Ctx, base_ms: FloatArray, ms: FloatArray
) -> tuple[FloatArray, FloatArray, float, float, FloatArray, float]:
    """The terms the rules judge a model's validation mean squares ``ms`` by against the
    model before's ``base_ms``: each experiment's weight (its noise floor's, all 1 without
    kind floors) and floor (m²), the floor-weighted RMS gaps before and after (m), and the
    log ratios and geometric shrink of :func:`~.select.relative_terms`."""
    w = ctx.validation_weights if len(base_ms) == ctx.n_validation else np.ones(len(base_ms))
    wrms0 = math.sqrt(float(np.mean(w * base_ms)))
    wrms1 = math.sqrt(float(np.mean(w * ms)))
    floor_ms = ctx.floor**2 / w
    log_ratios, geometric_shrink = relative_terms(base_ms, ms, floor_ms)
    return w, floor_ms, wrms0, wrms1, log_ratios, geometric_shrink


def judged_shrink(ctx: _Ctx, base_ms: FloatArray, ms: FloatArray) -> float:
    """The validation shrink from ``base_ms`` to ``ms`` (mean squares per validation
    experiment, m²) in the terms of :attr:`DiagnosisSettings.significance`: the geometric
    shrink (``"relative"``) or the floor-weighted pooled one; negative: worse."""
    _, _, wrms0, wrms1, _, geometric = _shrink_terms(ctx, base_ms, ms)
    if ctx.st.significance == "relative":
        return geometric
    return 1.0 - wrms1 / wrms0 if wrms0 > 0 else 0.0


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
    null_params: Sequence[tuple[str, Param]] = (),
    *,
    divisor: int | None = None,
) -> CandidateResult:
    """Judge fitted candidate results against the model before (``base_ms``). The bootstrap
    resamples validation moves (``units``/``base_units``) when both are given, else
    experiments. ``null_params``: the candidate's parameters that have a null value, for
    :attr:`DiagnosisSettings.null_test`. ``divisor``: the p is judged at
    :attr:`DiagnosisSettings.p_value` over it (Holm's step-down over the family,
    :func:`_judged_holm`), not over the whole family (Bonferroni)."""
    st = ctx.st
    alpha = ctx.p_level
    level = f"{alpha:.2g}" + (
        f" ({st.p_value:g} over {ctx.family} candidates)" if alpha != st.p_value else ""
    )
    if divisor is not None and st.multiple_testing and divisor != max(ctx.family, 1):
        alpha = st.p_value / divisor
        level = f"{alpha:.2g} (Holm: {st.p_value:g} over {divisor} of {ctx.family} candidates)"
    # The rules weigh each validation experiment by its own noise floor (all 1 without
    # kind floors): in units of the overall floor, a quiet experiment's gap counts as much
    # as a loud one's relative to what noise alone gives there. The move units come
    # weighted from :meth:`_Ctx.fit_and_validate`.
    w, floor_ms, wrms0, wrms1, log_ratios, geometric_shrink = _shrink_terms(ctx, base_ms, ms)
    rms0 = math.sqrt(float(np.mean(base_ms)))
    rms1 = math.sqrt(float(np.mean(ms)))
    shrink = 1.0 - rms1 / rms0 if rms0 > 0 else 0.0
    weighted_shrink = 1.0 - wrms1 / wrms0 if wrms0 > 0 else 0.0
    penalty = st.penalty(k_params)
    weighted = bool(np.any(w != 1.0))
    wtag = " (floor-weighted)" if weighted else ""
    relative = st.significance == "relative"
    # The shrink the penalty and the large-gap rule judge.
    judged = geometric_shrink if relative else weighted_shrink
    # A large explained gap: far above the floor, and most of it removed.
    large = (
        st.large_gap_factor > 0.0
        and wrms0 >= st.large_gap_factor * ctx.floor
        and judged >= st.large_shrink
    )
    reasons = []
    # ``ok``: every rule but the bootstrap's level (``p_ok``) holds.
    ok = True
    p_ok = True
    if relative:
        # An experiment at its floor before and after (log ratio 0 after the clamp) says
        # nothing for or against the candidate: it is left out of the bootstrap, as a
        # signed-rank test drops zero differences. Kept, two such experiments out of four
        # would hold p at 1/16 whatever the others show.
        informative: int | None = int(np.count_nonzero(log_ratios))
        p = bootstrap_p(log_ratios[log_ratios != 0.0], st.bootstrap, st.seed + 1000 + index)
        if p >= alpha and not large:
            p_ok = False
            reasons.append(
                f"bootstrap over validation experiments (log ratios): p = {p:.3f} ≥ {level}"
            )
        if geometric_shrink <= penalty:
            ok = False
            reasons.append(
                f"geometric shrink {geometric_shrink:.1%} ≤ complexity penalty {penalty:.0%}"
            )
        gap_text = (
            f"validation gaps: geometric shrink {geometric_shrink:.0%} (pooled "
            f"{rms0 * 1e9:.0f} → {rms1 * 1e9:.0f} nm, shrink {shrink:.0%})"
        )
    else:
        informative = None
        d = base_ms - ms
        du = (
            base_units - units
            if units is not None and base_units is not None and len(units) == len(base_units)
            else w * d
        )
        p = bootstrap_p(du, st.bootstrap, st.seed + 1000 + index)
        if p >= alpha and not large:
            p_ok = False
            reasons.append(f"bootstrap over validation moves{wtag}: p = {p:.3f} ≥ {level}")
        if weighted_shrink <= penalty:
            ok = False
            reasons.append(f"shrink{wtag} {weighted_shrink:.1%} ≤ complexity penalty {penalty:.0%}")
        floor_gain = st.floor_factor * ctx.floor**2 / ctx.n_validation
        gain = float(np.mean(w * d))
        if gain <= floor_gain:
            ok = False
            reasons.append(
                f"mean-square gain {gain:.3g} m² ≤ noise-and-refit floor {floor_gain:.3g} m²"
            )
        gap_text = (
            f"validation gap {rms0 * 1e9:.0f} → {rms1 * 1e9:.0f} nm (shrink {shrink:.0%}"
            + (f"; floor-weighted {wrms0 * 1e9:.0f} → {wrms1 * 1e9:.0f} nm" if weighted else "")
            + ")"
        )
    marks_note = ""
    if name in FRICTION_MODELS and st.friction_model_share > 0.0:
        share = 1.0 - (1.0 - judged) ** 2 if judged < 1.0 else 1.0
        if share < st.friction_model_share and name in ctx.mark_supported:
            marks_note = (
                f"; it explains {share:.0%} of the gap's mean square, under "
                f"{st.friction_model_share:.0%}, but {ctx.mark_supported[name]:.0%} of the "
                "χ² of the ramp marks the model before misses (the friction's speed "
                "dependence, which a law's presliding form error does not reach)"
            )
        elif share < st.friction_model_share:
            ok = False
            reasons.append(
                f"a friction law explains {share:.0%} of the gap's mean square, under "
                f"{st.friction_model_share:.0%}: a partial fit of the nominal law's form "
                "error, which every other law also leaves"
            )
    null_p = null_test_p(fits[0], null_params)
    null_failed = bool(st.null_test and null_p is not None and null_p >= st.p_value and not large)
    if null_failed:
        ok = False
        sizes = ", ".join(
            f"{n.split('.', 1)[1]} = {_with_se(fits[0], n)} {p.unit} (none: {p.null:g})"
            for n, p in null_params
            if n in fits[0].values
        )
        reasons.append(
            f"the fitted size does not differ from none ({sizes}): Wald p = {null_p:.3f} ≥ "
            f"{st.p_value:g}"
        )
    if wrms0 <= st.explainable_factor * ctx.floor:
        ok = False
        reasons.append(
            f"the gap before{wtag} ({wrms0 * 1e9:.0f} nm) is within {st.explainable_factor}× "
            f"the noise floor ({ctx.floor * 1e9:.0f} nm): nothing left to explain"
        )
    large_text = (
        f" (≥ {level}, but the gap before is {wrms0 / ctx.floor:.0f}× the noise "
        f"floor and {judged:.0%} of it is removed: a large explained gap)"
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
    if widens_pooled_gap(shrink, st.max_pooled_widening):
        ok = False
        reasons.append(
            f"the pooled validation gap widens ({rms0 * 1e9:.0f} → {rms1 * 1e9:.0f} nm, "
            f"shrink {shrink:.0%}, beyond −{st.max_pooled_widening:.0%}): the effect trades "
            "one experiment's residual for another's"
        )
    if ok and p_ok:
        reasons.append(
            gap_text
            + f", bootstrap p = {p:.3f}"
            + (large_text if p >= alpha else "")
            + ("" if command_ratio is None else f", command residual × {command_ratio:.2f}")
            + marks_note
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
        geometric_shrink=geometric_shrink,
        p_value=p,
        significant=ok and p_ok,
        other_rules_pass=ok,
        reasons=reasons,
        setting=setting,
        index=index,
        k_params=k_params,
        validation_units=units,
        validation_floor_ms=floor_ms,
        informative_experiments=informative,
        p_level=alpha,
        null_params=tuple(null_params),
        null_p_value=null_p,
        null_failed=null_failed,
    )


def _with_se(fit: Fit, name: str) -> str:
    """A fitted value with its standard error (where finite), 3 significant digits."""
    v = fit.values[name]
    se = fit.std_errors.get(name)
    return f"{v:.3g} ± {se:.2g}" if se is not None and math.isfinite(se) else f"{v:.3g}"
