"""Choosing between fitted candidates.

Pooled significance (``significance = "pooled"``; documented in docs/diagnosis.md)
    A candidate is *significant* when all hold: (1) its validation mean-square gap is lower
    than the nominal model's by more than the noise floor allows: the bootstrap over
    validation experiments (resampled with replacement) gives a reduction ≤ 0 in fewer than
    5 % of resamples; (2) the RMS shrink exceeds a complexity penalty of
    ``0.03 + 0.02·(number of parameters)``; (3) the reduction of the mean square exceeds
    ``1.5 ×`` the floor's mean square divided by the number of validation experiments (what
    refitting to noise can buy).

Ranking (:attr:`~nanostage.diagnosis.settings.DiagnosisSettings.ranking`)
    ``"relative"`` (the default) orders the candidates by the mean over the validation
    experiments of log(mean-square gap): each experiment counts by the factor a candidate
    cuts *its* gap, whatever its size, so a long step whose gap is a hundred times a
    micro-step's does not alone decide between candidates that differ by factors of 3–6 on
    the dwells, micro-steps and ramps. ``"pooled"`` orders them by the pooled RMS gap (the
    earlier rule).

Relative significance (:attr:`~nanostage.diagnosis.settings.DiagnosisSettings.significance`)
    ``"relative"`` (the default) judges in the relative ranking's terms. Per validation
    experiment, the log ratio of the mean-square gap before to the candidate's, each
    clamped at that experiment's noise floor squared (a gap cut below the floor is cut to
    noise, and counts no further; :func:`relative_terms`). A candidate is significant when
    all hold: (1) the bootstrap over the validation experiments gives a mean log ratio
    ≤ 0 in fewer than 5 % of resamples (an experiment at its floor before and after, log
    ratio 0, is left out: it says nothing either way); (2) the geometric shrink,
    ``1 − exp(−mean log ratio / 2)``, exceeds the complexity penalty. What does not depend
    on the candidate holds in both modes: the gap before must exceed ``1.5 ×`` the noise
    floor (each experiment weighted by its own floor: there is something to explain), the
    large-explained-gap rule (with the geometric shrink here), and the command check.
    ``"pooled"`` applies the rules above. Under ``"relative"`` one rule looks at the pooled
    gap: a candidate that widens it by more than
    :attr:`~nanostage.diagnosis.settings.DiagnosisSettings.max_pooled_widening` (its
    small gaps cut, its large ones made worse) is not significant.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ..fitting import Param, simplest_of_ties
from .fit import Fit
from .settings import RANKINGS, SIGNIFICANCES, DiagnosisSettings, FloatArray

#: A mean square below this (m²) counts as this in the relative ranking (log of zero).
_TINY_MS_M2 = 1e-40


def _log_ms(ms: FloatArray, floor_ms: FloatArray | float = _TINY_MS_M2) -> FloatArray:
    """log(mean square / m²) per validation experiment, each clamped at ``floor_ms`` (by
    default a zero counted as :data:`_TINY_MS_M2`)."""
    out: FloatArray = np.log(np.maximum(ms, np.maximum(floor_ms, _TINY_MS_M2)))
    return out


__all__ = [
    "RANKINGS",
    "SIGNIFICANCES",
    "CandidateResult",
    "bootstrap_p",
    "holm_levels",
    "indistinguishable",
    "log_occam_factor",
    "null_test_p",
    "pick_winner",
    "relative_terms",
    "significance_mode",
    "too_few_to_test",
    "turned_down",
    "without_unsupported",
]


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
    #: The geometric shrink over the validation experiments (:func:`relative_terms`): what
    #: the relative significance applies the complexity penalty to.
    geometric_shrink: float
    p_value: float
    significant: bool
    reasons: list[str]
    setting: int | None = None
    #: The candidate's seed offset (:func:`~nanostage.diagnosis.loop.candidate_seed`: seeds
    #: its fits and bootstrap) and its parameter count (the complexity penalty), kept so
    #: that it can be judged again against a new baseline.
    index: int = 0
    k_params: int = 0
    #: Each validation move's share of the mean square (the bootstrap's units).
    validation_units: FloatArray | None = None
    #: Log Occam factor of the candidate's own parameters (:func:`log_occam_factor`).
    log_occam: float = 0.0
    #: Each validation experiment's noise floor as a mean square, m² (None: none known):
    #: the relative ranking counts no experiment's gap below it, like the relative
    #: significance (:func:`relative_terms`).
    validation_floor_ms: FloatArray | None = None
    #: How many validation experiments the relative significance's bootstrap resampled:
    #: those whose gap lies above their noise floor before or after (None: the pooled
    #: significance, which resamples moves). See :func:`too_few_to_test`.
    informative_experiments: int | None = None
    #: Unit of each of the candidate's own parameters (``effect.param`` → unit).
    units: Mapping[str, str] = field(default_factory=dict)
    #: The level ``p_value`` was judged at: :attr:`DiagnosisSettings.p_value`, over the
    #: number of candidates judged together with :attr:`DiagnosisSettings.multiple_testing`.
    p_level: float = 0.05
    #: The candidate's parameters that have a null value (``effect.param``, parameter),
    #: and the p of the Wald test of ``fit`` against them (:func:`null_test_p`; None: no
    #: such parameter, or no covariance).
    null_params: tuple[tuple[str, Param], ...] = ()
    null_p_value: float | None = None
    #: The null test failed (:attr:`DiagnosisSettings.null_test`): the fitted size does not
    #: differ from none and the explained gap is not large.
    null_failed: bool = False
    #: Every rule of significance but the bootstrap's level holds (:func:`holm_levels`).
    other_rules_pass: bool = True

    @property
    def log_ms(self) -> FloatArray:
        """log(mean-square gap / m²) per validation experiment, each clamped at its noise
        floor (:attr:`validation_floor_ms`, where known): a change below the floor is
        noise, and neither ranks nor ties a candidate."""
        if self.validation_floor_ms is None:
            return _log_ms(self.validation_ms)
        return _log_ms(self.validation_ms, self.validation_floor_ms)

    @property
    def mean_log_ms(self) -> float:
        """Mean over the validation experiments of :attr:`log_ms`: the relative ranking's
        key (``inf`` without validation experiments)."""
        if len(self.validation_ms) == 0:
            return math.inf
        return float(np.mean(self.log_ms))

    @property
    def geometric_rms_m(self) -> float:
        """The geometric mean over the validation experiments of their RMS gaps, each at
        least its noise floor, m (the relative ranking's key in metres)."""
        return math.exp(0.5 * self.mean_log_ms)

    def to_dict(self) -> dict[str, Any]:
        units = self.units
        return {
            "effect": self.effect,
            "validation_rms_m": self.validation_rms_m,
            "validation_geometric_rms_m": self.geometric_rms_m,
            "shrink": self.shrink,
            "weighted_shrink": self.weighted_shrink,
            "geometric_shrink": self.geometric_shrink,
            "significant": self.significant,
            "p_value": self.p_value,
            "p_level": self.p_level,
            "null_p_value": self.null_p_value,
            "informative_validation_experiments": self.informative_experiments,
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


def too_few_to_test(n: int, p_value: float) -> bool:
    """Whether ``n`` validation experiments are too few for any test over them to reach
    ``p_value``: an exact sign-flip test over ``n`` values cannot give less than 2⁻ⁿ (all
    of them improved), so ``n`` < log₂(1/``p_value``) (fewer than 5 at 0.05). The bootstrap
    the relative significance uses gives p = 0 whenever all ``n`` improve, however few, small
    and scattered they are: below this count its p is no evidence of consistency."""
    return 0.5**n > p_value


def holm_levels(
    p_values: Sequence[float],
    p_value: float,
    family: int,
    others_pass: Sequence[bool] | None = None,
) -> list[int]:
    """Holm's step-down over a family of ``family`` candidates (at least ``len(p_values)``;
    a candidate of the family without a p counts as not significant): for each p (in the
    given order), the number of candidates its level divides ``p_value`` by. The smallest p
    is judged at ``p_value``/``family``, as Bonferroni judges every p; the k-th smallest
    (from 0) at ``p_value``/(``family`` − k) once every smaller one passed its level. From
    the first p that fails its level on, every larger p is judged at that same level (and,
    without ``others_pass``, fails it). The family-wise error rate is ``p_value`` under any
    dependence between the tests, as with Bonferroni; what passes Bonferroni passes here.
    Ties of p keep the given order.

    ``others_pass`` (per p: whether the candidate passes every other rule of
    significance): a step passes only where that holds too, so the step-down stops at the
    first candidate that is not significant, and the ones after it are judged at its level.
    Then a family with nothing significant under Bonferroni has nothing significant here
    either: its smallest p is judged at Bonferroni's level and, failing that or another
    rule, leaves every other p at Bonferroni's level too."""
    m = max(family, len(p_values))
    if others_pass is not None and len(others_pass) != len(p_values):
        raise ValueError(
            f"others_pass has {len(others_pass)} entries; expected one per p ({len(p_values)})"
        )
    order = sorted(range(len(p_values)), key=lambda i: (p_values[i], i))
    out = [m] * len(p_values)
    divisor = m
    passing = True
    for k, i in enumerate(order):
        if passing:
            divisor = m - k
            passing = p_values[i] < p_value / divisor and (
                others_pass is None or bool(others_pass[i])
            )
        out[i] = divisor
    return out


def bootstrap_p(d: FloatArray, n_boot: int, seed: int) -> float:
    """Fraction of bootstrap resamples (of the units: validation moves) with mean reduction
    ≤ 0."""
    if len(d) == 0:
        return 1.0
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(d), size=(n_boot, len(d)))
    means = d[idx].mean(axis=1)
    return float(np.mean(means <= 0.0))


def relative_terms(
    before_ms: FloatArray, after_ms: FloatArray, floor_ms: FloatArray
) -> tuple[FloatArray, float]:
    """The relative significance's terms (module docstring) from the mean-square gaps of
    the validation experiments before and after, m², and each one's noise floor squared:
    the log ratios (each mean square clamped at its floor; positive: the gap shrank) and
    the geometric shrink ``1 − exp(−mean/2)`` (0 without experiments)."""
    before = np.asarray(before_ms, dtype=np.float64)
    after = np.asarray(after_ms, dtype=np.float64)
    floor = np.asarray(floor_ms, dtype=np.float64)
    if not before.shape == after.shape == floor.shape:
        raise ValueError(
            f"relative_terms: {before.shape}, {after.shape} and {floor.shape} experiments "
            "before, after and floors: expected the same"
        )
    if before.size == 0:
        return np.zeros(0), 0.0
    d: FloatArray = _log_ms(before, floor) - _log_ms(after, floor)
    return d, 1.0 - math.exp(-0.5 * float(np.mean(d)))


def significance_mode(significance: str) -> str:
    """``significance`` checked against :data:`SIGNIFICANCES` (a clear error otherwise)."""
    if significance not in SIGNIFICANCES:
        raise ValueError(
            f"DiagnosisSettings.significance = {significance!r}: expected one of "
            f"{', '.join(SIGNIFICANCES)}"
        )
    return significance


def rank_key(ranking: str) -> Callable[[CandidateResult], float]:
    """The sort key of a round's candidates (smallest first) under ``ranking`` (one of
    :data:`RANKINGS`)."""
    if ranking not in RANKINGS:
        raise ValueError(
            f"DiagnosisSettings.ranking = {ranking!r}: expected one of {', '.join(RANKINGS)}"
        )
    if ranking == "pooled":
        return lambda r: r.validation_rms_m
    return lambda r: r.mean_log_ms


def indistinguishable(a: CandidateResult, b: CandidateResult, ranking: str = "relative") -> bool:
    """Whether the validation data cannot tell candidates ``a`` and ``b`` apart under
    ``ranking``. ``"pooled"``: their RMS gaps lie within 25 % of each other and the mean
    difference of their per-experiment mean squares is within two standard errors (over
    the validation experiments). ``"relative"``: the same in relative terms, on the
    per-experiment differences of log(mean square): their geometric-mean RMS gaps lie
    within 25 % of each other and the mean log ratio is within two standard errors. With
    fewer than two validation experiments nothing can be told apart."""
    rank_key(ranking)  # checks the name
    if ranking == "relative":
        la, lb = a.log_ms, b.log_ms
        d = la - lb
        # Geometric-mean RMS within 25 %: half the mean log ratio within log 1.25.
        close = abs(float(np.mean(la)) - float(np.mean(lb))) <= 2.0 * math.log(1.25)
    else:
        d = a.validation_ms - b.validation_ms
        close = abs(a.validation_rms_m - b.validation_rms_m) <= 0.25 * min(
            a.validation_rms_m, b.validation_rms_m
        )
    if len(d) < 2:
        return True
    se = float(np.std(d, ddof=1) / math.sqrt(len(d)))
    return close and abs(float(np.mean(d))) <= 2.0 * se


def _constrained(cov: FloatArray) -> list[int]:
    """The parameters of a covariance the data constrain: a positive variance and a finite
    row and column (the pseudo-inverse gives an unconstrained parameter variance 0)."""
    return [
        i
        for i in range(cov.shape[0])
        if cov[i, i] > 0.0 and bool(np.all(np.isfinite(cov[i])) and np.all(np.isfinite(cov[:, i])))
    ]


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
    keep = _constrained(sub)
    if not keep:
        return out
    sub = sub[np.ix_(keep, keep)]
    lam = np.linalg.eigvalsh(sub)
    tiny = float(np.max(lam)) * len(keep) * np.finfo(np.float64).eps
    for v in lam:
        if v > tiny:
            out += 0.5 * math.log(min(1.0, 2.0 * math.pi * float(v)))
    return out


def null_test_p(fit: Fit, params: Sequence[tuple[str, Param]]) -> float | None:
    """The p of the Wald test that the fitted values of ``params`` (``fit.values`` names and
    their parameters, each with a :attr:`~nanostage.fitting.Param.null`) differ jointly
    from their nulls: W = δᵀ Σ⁺ δ, with δ the differences and Σ their covariance in the
    fit's normalised coordinates (:attr:`Fit.unit_covariance`, which holds the free nominal
    parameters' correlations), against χ² with rank(Σ) degrees of freedom. A parameter the
    data do not constrain (variance 0 from the pseudo-inverse, or not finite) says nothing
    and is left out; left with none, p = 1. None when no parameter has a null, or the fit
    has no covariance (no test)."""
    from scipy.stats import chi2

    if not any(p.null is not None for _, p in params):
        return None
    fitted = list(fit.values)
    cov = fit.unit_covariance
    tested = [(n, p) for n, p in params if p.null is not None and n in fit.values]
    if not tested or cov.shape != (len(fitted), len(fitted)):
        return None
    idx = [fitted.index(n) for n, _ in tested]
    delta = np.array([p.to_unit(fit.values[n]) - p.to_unit(p.null) for n, p in tested])  # type: ignore[arg-type]
    sub = cov[np.ix_(idx, idx)]
    keep = _constrained(sub)
    if not keep:
        return 1.0
    sub = sub[np.ix_(keep, keep)]
    d = delta[keep]
    rank = int(np.linalg.matrix_rank(sub, hermitian=True))
    w = float(d @ np.linalg.pinv(sub, hermitian=True) @ d)
    return float(chi2.sf(w, rank))


def widens_pooled_gap(shrink: float, max_pooled_widening: float) -> bool:
    """Whether a pooled RMS ``shrink`` widens the gap by more than ``max_pooled_widening``
    (:attr:`~nanostage.diagnosis.settings.DiagnosisSettings.max_pooled_widening`; negative:
    the rule is off, never)."""
    return max_pooled_widening >= 0.0 and shrink < -max_pooled_widening


def without_unsupported(
    judged: Sequence[CandidateResult],
    own: Mapping[str, CandidateResult],
    max_pooled_widening: float = -1.0,
) -> list[CandidateResult]:
    """``judged`` (a round's candidates judged on every experiment, each refitted on folds
    that hold validation experiments too) with every significant one whose own fit of the
    round (``own``: by effect, fitted on the training experiments; the fit a selection
    carries into the model) failed the null test marked not significant, with the reason:
    the effect it would name is not there in the fit the selection would carry, only in
    fits that saw the validation experiments. With ``max_pooled_widening`` ≥ 0
    (:attr:`~nanostage.diagnosis.settings.DiagnosisSettings.max_pooled_widening`), so is
    one whose own fit widens the pooled validation gap by more than that fraction: the
    model the selection would carry makes the gap the report gives larger."""
    out = []
    for r in judged:
        mine = own.get(r.effect)
        if r.significant and mine is not None and mine.null_failed:
            reason = (
                "its fit on the training experiments, which a selection carries, does not "
                "differ from none"
                + ("" if mine.null_p_value is None else f" (Wald p = {mine.null_p_value:.3f})")
                + ": the effect shows only in refits that saw the validation experiments"
            )
            r = replace(r, significant=False, reasons=[reason, *r.reasons])
        elif (
            r.significant
            and mine is not None
            and widens_pooled_gap(mine.shrink, max_pooled_widening)
        ):
            reason = (
                "its fit on the training experiments, which a selection carries, widens the "
                f"pooled validation gap (shrink {mine.shrink:.0%}, beyond "
                f"−{max_pooled_widening:.0%})"
            )
            r = replace(r, significant=False, reasons=[reason, *r.reasons])
        out.append(r)
    return out


def turned_down(
    results: Sequence[CandidateResult], reasons: Mapping[str, str]
) -> list[CandidateResult]:
    """``results`` with each candidate named in ``reasons`` (effect → why) not significant,
    its reason added once, first (before the judging's words for it, which may be a pass);
    the others as they are. Same order."""
    out = []
    for r in results:
        why = reasons.get(r.effect)
        if why is not None:
            given = r.reasons if why in r.reasons else [why, *r.reasons]
            r = replace(r, significant=False, reasons=given)
        out.append(r)
    return out


def pick_winner(
    results: Sequence[CandidateResult],
    st: DiagnosisSettings,
    signature_chi_squares: (
        Callable[[Sequence[CandidateResult]], Sequence[tuple[float, int]]] | None
    ) = None,
    signature_margin: float = 0.0,
) -> CandidateResult | None:
    """The candidate a round selects from its results (best first by
    :attr:`DiagnosisSettings.ranking`): the first significant one; with
    :attr:`DiagnosisSettings.occam_tie_break`, among it and the significant candidates the
    data cannot tell from it, the one with the largest Occam factor (the first in that
    order when equal). None when nothing is significant.

    With ``signature_chi_squares`` (the tied candidates → the χ² of each fitted model's
    simulated signature against the measured one and the number of features in it,
    :func:`~nanostage.diagnosis.signatures.tie_chi_squares`: over the marks the tied
    effects make, each in units of the closest tied model's miss of it where that exceeds
    its errors) and
    ``signature_margin`` > 0, the tied candidates are first narrowed to those whose χ² lies
    within ``signature_margin`` of the closest one. What the gap cannot tell apart, the
    traces' limit cycles, rest commands, ramp commands, breakaways and reversal lags may.
    Without them, or with one tied candidate, the choice is as above."""
    best = next((r for r in results if r.significant), None)
    if best is None:
        return None
    tied = [
        r
        for r in results
        if r.significant and (r is best or indistinguishable(best, r, st.ranking))
    ]
    if signature_chi_squares is not None and signature_margin > 0.0 and len(tied) > 1:
        d = [x for x, _ in signature_chi_squares(tied)]
        closest = min(d)
        tied = [r for r, x in zip(tied, d, strict=True) if x <= closest + signature_margin]
    if not st.occam_tie_break:
        return tied[0]
    # The largest Occam factor is the least complexity (the first in gap order when equal).
    return simplest_of_ties(tied, lambda r: True, lambda r: -r.log_occam)
