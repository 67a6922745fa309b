"""Fitting one model to the training experiments: :class:`FitProblem` (multi-start least
squares over the free parameters and a candidate's effect parameters) and its result
:class:`Fit`."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.optimize import least_squares
from scipy.stats import qmc

from ..config import System
from ..experiment import Experiment
from .candidates import Param
from .objective import (
    HoldPlan,
    SimulationCache,
    apply_gap_plan,
    autocorrelation_time,
    command_plan,
    gap_plan,
    rms_of,
    simulate_readings_and_commands,
)
from .scatter import discount_level
from .settings import FAILED_GAP_M, Adapt, DiagnosisSettings, FloatArray

__all__ = [
    "AT_BOUND",
    "Fit",
    "FitProblem",
    "SecantJacobian",
    "at_bounds",
]


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
        command_weights_m_per_v: Mapping[str, float] | None = None,
        level_directions: Mapping[str, tuple[FloatArray, float]] | None = None,
    ) -> None:
        self.params = list(params)
        #: Per experiment (by name), the direction of a run-to-run friction level change in
        #: its gap and the factor its component along it is kept by, fixed for the problem;
        #: missing: the gap as it is (:mod:`~nanostage.diagnosis.scatter`,
        #: :func:`~nanostage.diagnosis.scatter.discount_level`).
        self.level_directions = dict(level_directions or {})
        #: Weight of the command gap against the position gap per experiment (by name),
        #: m/V: with a weight > 0 the gap of an experiment with a measured command stacks
        #: the position gap (m) and the command gap (V) times the weight; 0 or missing
        #: leaves the command out of the experiment's gap.
        self.command_weights_m_per_v = dict(command_weights_m_per_v or {})
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
        #: :func:`command_plan` of each experiment with a measured command.
        self._command_plans: dict[str, list[HoldPlan]] = {}
        #: An orthonormal basis (columns) of directions taken out of every scaled residual
        #: vector the fit sees (None: none): the span of the free nominal parameters'
        #: Jacobian, so that a screening fit with them held judges a candidate as if they
        #: had moved to their linearised best (variable projection;
        #: :attr:`DiagnosisSettings.screen_moves_nominal`).
        self.projection: FloatArray | None = None

    def _uses_command(self, e: Experiment) -> bool:
        return self.command_weights_m_per_v.get(e.name, 0.0) > 0.0 and e.command_v is not None

    def residuals(self, system: System, experiments: Sequence[Experiment]) -> list[FloatArray]:
        """Per-experiment gap (measured − simulated mean reading; followed by the weighted
        command gap where the problem uses the command, :attr:`command_weights_m_per_v`)."""
        return self.residuals_of([system], experiments)[0]

    def residuals_and_commands(
        self, system: System, experiments: Sequence[Experiment]
    ) -> tuple[list[FloatArray], list[float | None]]:
        """:meth:`residuals`, and each experiment's mean-square command residual (V², None
        where the experiment has no measured command or the gap uses it already)."""
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
                gap = apply_gap_plan(self._plans[e.name], e.position_m, reading)
                if self._uses_command(e):
                    assert e.command_v is not None
                    if e.name not in self._command_plans:
                        self._command_plans[e.name] = command_plan(self._plans[e.name], e.command_v)
                    cgap = apply_gap_plan(self._command_plans[e.name], e.command_v, cmd)
                    gap = np.concatenate([gap, self.command_weights_m_per_v[e.name] * cgap])
                level = self.level_directions.get(e.name)
                if level is not None:
                    gap = discount_level(gap, level)
                gaps.append(gap)
                # The command's own check (a channel the fit does not use), compared as the
                # gap would compare it (a limit cycle's phase is no residual); None where the
                # command is part of the gap already.
                if e.command_v is None or self._uses_command(e):
                    command.append(None)
                else:
                    if e.name not in self._command_plans:
                        self._command_plans[e.name] = command_plan(self._plans[e.name], e.command_v)
                    r = apply_gap_plan(self._command_plans[e.name], e.command_v, cmd)
                    command.append(float(np.mean(r**2)))
            out.append((gaps, command))
        return out

    def _failed_vector(self) -> FloatArray:
        # A failed simulation (or an invalid combination, e.g. a Coulomb level above the
        # static one) is a very bad fit, not a crash: a gap of 1 mm in every sample, far
        # worse than any valid model (the residuals are in counts).
        return np.concatenate(
            [
                np.full(n, FAILED_GAP_M / (self.scale_m * math.sqrt(n)))
                for n in (
                    len(e.time_s) * (2 if self._uses_command(e) else 1) for e in self.experiments
                )
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
        q = self.projection
        for maybe in systems:
            r = None if maybe is None else next(it)
            v = self._failed_vector() if r is None else self._scaled(r)
            out.append(v if q is None else v - q @ (q.T @ v))
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
        scan_only: Sequence[bool] | None = None,
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
        the next best scanned points (better than the warm start) as further starts. With
        warm parameters and a ``prior`` start, the same points are scanned from the prior
        start too, and it takes the drawn values of the best of them (if better).
        ``scan_only`` (one flag per parameter): the scan draws only the flagged ones among
        the drawn parameters (the others keep their start values in it); None: all."""
        k = len(self.params)
        self.scale_m = self.build([p.initial for _, p in self.params]).encoder.count_m
        if k == 0:
            system = self.build([])
            res = self.residuals(system, self.experiments)
            return Fit(
                values={},
                std_errors={},
                train_rms_m=rms_of(res),
                n_evaluations=1,
                system=system,
            )
        first = np.array([1.0 + p.to_unit(p.initial) for _, p in self.params])
        starts = [first]
        second: FloatArray | None = None
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
            every = list(range(k - n_draw, k))
            drawn = [i for i in every if scan_only is None or scan_only[i]] or every
            rows = qmc.LatinHypercube(d=len(drawn), seed=seed + 7919).random(scan)

            def scanned_from(start: FloatArray) -> list[FloatArray]:
                # The scanned points that beat `start` (its drawn parameters at the scan's
                # rows, the others kept), best first.
                cands = []
                for row in rows:
                    u = start.copy()
                    u[drawn] = 1.0 + row
                    cands.append(u)
                costs = [float(np.sum(v**2)) for v in self._vectors([start, *cands])]
                return [
                    cands[i - 1]
                    for i in np.argsort(costs, kind="stable")
                    if i > 0 and costs[i] < costs[0]
                ]

            # The best `scan_starts` scanned points that beat the warm start, best first.
            best_scanned = scanned_from(first)[: max(scan_starts, 1)]
            if second is not None and n_warm > 0 and second is starts[-1]:
                # The prior start is scanned too, and takes its best values of the drawn
                # (effect) parameters: the warm free values may be bent to mimic the missing
                # effect (a calibration at its bounds), so that at them the effect's own
                # size fits worse than a token one; at the prior's unbent values, with the
                # effect at its best size there, lies the other basin worth a local fit.
                from_prior = scanned_from(second)
                if from_prior:
                    second[k - n_draw :] = from_prior[0][k - n_draw :]
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
        best_secant: SecantJacobian | None = None
        for u0 in starts:
            secant = (
                SecantJacobian(self, settings.diff_step, settings.jacobian_refresh)
                if settings.jacobian_refresh > 1
                else None
            )
            sol = least_squares(
                self._vector if secant is None else secant.fun,
                np.clip(u0, 1.0, 2.0),
                bounds=(1.0, 2.0),
                method="trf",
                jac="2-point" if secant is None else secant.jac,
                diff_step=settings.diff_step,
                max_nfev=settings.max_nfev_per_param * (k + 1),
                x_scale=1.0,
                xtol=1e-4,
                ftol=1e-4,
                gtol=1e-6,
                workers=self._batch_map if secant is None else None,
            )
            if best is None or sol.cost < best.cost:
                best, best_secant = sol, secant
        if best_secant is not None and not best_secant.fresh:
            # The uncertainties come from a difference Jacobian at the optimum, not from the
            # last rank-one update.
            best.jac = best_secant.differences(best.x, best.fun)
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


class SecantJacobian:
    """The Jacobian of a :class:`FitProblem`'s scaled residual for one
    :func:`scipy.optimize.least_squares` run (``fun`` and ``jac`` go to it): forward
    differences, as scipy's ``2-point`` takes them (relative step ``diff_step``, backward
    where the step would leave the upper bound 2; all points in one batch), at the start,
    after a rejected trial step and at every ``refresh``-th accepted step; between them,
    Broyden's rank-one update from the accepted step (``trf`` asks for the Jacobian only
    at accepted points). A difference Jacobian costs one simulation batch per parameter,
    the update none: with a dozen parameters the fit then runs a fraction of the
    simulations. A rejected step means the linear model was poor, so the next Jacobian is
    a difference one."""

    def __init__(self, problem: FitProblem, diff_step: float, refresh: int) -> None:
        self.problem = problem
        self.diff_step = diff_step
        self.refresh = refresh
        #: Whether the last Jacobian returned was a difference one (not an update).
        self.fresh = False
        self._evaluated: tuple[FloatArray, FloatArray] | None = None
        self._calls = 0  # residual evaluations since the last Jacobian
        self._updates = 0  # rank-one updates since the last difference Jacobian
        self._last: tuple[FloatArray, FloatArray, FloatArray] | None = None

    def fun(self, u: FloatArray) -> FloatArray:
        f = self.problem._vector(u)
        self._evaluated = (np.array(u, dtype=np.float64), f)
        self._calls += 1
        return f

    def differences(self, u: FloatArray, f: FloatArray) -> FloatArray:
        """The forward-difference Jacobian at ``u`` (residual ``f``)."""
        u = np.asarray(u, dtype=np.float64)
        h = self.diff_step * np.maximum(1.0, np.abs(u))
        h = np.where(u + h > 2.0, -h, h)
        points = []
        for i, hi in enumerate(h):
            x = u.copy()
            x[i] = u[i] + hi
            points.append(x)
        steps = [x[i] - u[i] for i, x in enumerate(points)]
        columns = self.problem._vectors(points)
        return np.column_stack([(c - f) / d for c, d in zip(columns, steps, strict=True)])

    def jac(self, u: FloatArray) -> FloatArray:
        u = np.array(u, dtype=np.float64)
        rejected = self._calls > 1
        e = self._evaluated
        f = e[1] if e is not None and np.array_equal(e[0], u) else self.fun(u)
        last = self._last
        if last is None or rejected or self._updates + 1 >= self.refresh:
            jac = self.differences(u, f)
            self._updates, self.fresh = 0, True
        else:
            x0, f0, j0 = last
            dx = u - x0
            norm2 = float(dx @ dx)
            jac = j0 + np.outer(f - f0 - j0 @ dx, dx / norm2) if norm2 > 0.0 else j0
            self._updates, self.fresh = self._updates + 1, False
        self._last = (u, f, jac)
        self._calls = 0
        return jac


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


#: A free parameter within this share of its range from a bound (in the fit's normalised
#: coordinates: log space for a log parameter) is reported as at that bound.
AT_BOUND = 0.01


def at_bounds(fit: Fit, free: Sequence[tuple[str, Param]]) -> list[dict[str, Any]]:
    """The free parameters ``free`` that ``fit`` left at (within :data:`AT_BOUND` of) one of
    their bounds: ``parameter``, ``value``, ``bound`` (``"lower"`` or ``"upper"``) and
    ``limit`` (the bound's value). A calibration that drives a parameter of the nominal
    model to its bound bends it to fit something the model does not have: the candidates
    are judged from that calibration, so an effect it has absorbed can look like nothing
    (an amplifier lag absorbed by the rotor inertia at its upper bound and the table
    friction at its lower one)."""
    out: list[dict[str, Any]] = []
    for name, p in free:
        if name not in fit.values:
            continue
        value = float(fit.values[name])
        u = p.to_unit(value)
        side = "lower" if u <= AT_BOUND else "upper" if u >= 1.0 - AT_BOUND else None
        if side is not None:
            out.append(
                {
                    "parameter": name,
                    "value": value,
                    "bound": side,
                    "limit": p.lower if side == "lower" else p.upper,
                }
            )
    return out
