"""Diagnosis settings: the knobs of one diagnosis run (starts, budgets, thresholds,
threads) and the progress lines it prints."""

from __future__ import annotations

import dataclasses
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from ..config import System
from ..experiment import Experiment
from .candidates import Candidate

FloatArray = npt.NDArray[np.float64]
#: The gap charged for a parameter set whose model is invalid or whose simulation fails, m.
FAILED_GAP_M = 1e-3
#: Turns the model into the system of one experiment (its controller gains).
Adapt = Callable[[System, Experiment], System]
#: The orders of a round's candidates (:attr:`DiagnosisSettings.ranking`).
RANKINGS = ("relative", "pooled")
#: The significance tests of a candidate (:attr:`DiagnosisSettings.significance`).
SIGNIFICANCES = ("relative", "pooled")

__all__ = [
    "DEFAULT_LEVEL_SCATTER",
    "RANKINGS",
    "SIGNIFICANCES",
    "DiagnosisSettings",
    "PhaseClock",
    "phase_totals",
    "print_progress",
    "with_starts",
]


#: The run-to-run friction level scatter assumed when none is given (relative, 1σ): a
#: real axis's static and Coulomb levels wander by a few per cent from run to run
#: (docs/diagnosis.md, *Run-to-run friction scatter*); 0 in a manifest turns it off.
DEFAULT_LEVEL_SCATTER = 0.01


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
    #: Every how many accepted steps of a fit its Jacobian is taken again by forward
    #: differences (one simulation batch per parameter); between them Broyden's rank-one
    #: update stands in (:class:`~nanostage.diagnosis.fit.SecantJacobian`), and after a
    #: rejected step it is always taken again. 1: differences at every step (scipy's
    #: ``2-point``, the earlier default). On the two speed cases of the independent
    #: family (development seed 10100, ``benches/diagnosis_speed.py``) 4 ran half the
    #: simulations; the compliance case took 192 s instead of 360 s with the same
    #: selection.
    jacobian_refresh: int = 4
    #: Resamples of each bootstrap p. Its Monte Carlo error is √(p(1−p)/n): at the levels
    #: a family of 8–17 candidates is judged at (0.003–0.006), 400 resamples left an error
    #: (0.003) as large as the level, so whether a p near it passed was decided by the
    #: resampling's seed (a p of 3 resamples in 400 against a level of 2); 10 000 bring it
    #: to a tenth of the level, for about 5 ms per candidate judged.
    bootstrap: int = 10000
    p_value: float = 0.05
    #: A round selects the best of the candidates it judges together, so each is judged
    #: at ``p_value`` over their number (Holm's step-down: the number not yet significant,
    #: :func:`~.select.holm_levels`; :attr:`CandidateResult.p_level`): with
    #: k candidates at 0.05 each, a gap that no candidate explains still passes one of them
    #: by chance up to k·5 % of the time. Where a round is judged again on every experiment
    #: (:attr:`cross_judge_folds`), that judgement's candidates are the family. The selected
    #: effects' p of the kept fresh-seed reports before this rule: every correct first
    #: selection 0 (of 400 resamples); every false alarm 0.010–0.033 among 5–7 candidates.
    multiple_testing: bool = True
    #: A candidate is significant only if its fitted size differs from none: the Wald test
    #: of its parameters that have a null value (:attr:`~nanostage.fitting.Param.null`: an
    #: offset, an asymmetry, a harmonic amplitude, a voltage limit) against that value, by
    #: the first fold's covariance, gives p < ``p_value`` (unless the gap explained is
    #: large). The gap test asks whether the candidate predicts better; this one whether
    #: the effect it names is there: a form error of the nominal model that a small offset
    #: partly takes up can pass the first with an offset whose confidence interval holds 0.
    #: Judged on every experiment (:attr:`cross_judge_folds`), a candidate whose own fit of
    #: the round fails it is not selected on the folds' refits
    #: (:func:`~nanostage.diagnosis.select.without_unsupported`).
    null_test: bool = True
    penalty_base: float = 0.03
    penalty_per_param: float = 0.02
    floor_factor: float = 1.5
    #: A candidate is significant only if the validation gap before exceeds this many
    #: noise floors (0 turns the rule off). Measured on benchmark seeds 12 and 13: off, it
    #: found three more dwell cases and made two false alarms in twelve no-effect cases.
    explainable_factor: float = 1.5
    #: Judge candidates with each validation experiment weighted by the inverse square of
    #: its own noise floor (:func:`experiment_floors_m`) instead of one floor for all.
    kind_floors: bool = True
    command_tolerance: float = 1.1
    #: A large explained gap is never discarded: a candidate that fails only the bootstrap
    #: (its gain concentrated in a few validation moves, which a handful of validation
    #: experiments cannot show to be consistent) is significant all the same when the
    #: floor-weighted gap before is at least :attr:`large_gap_factor` noise floors and the
    #: candidate removes at least :attr:`large_shrink` of it (RMS). 0 turns the rule off.
    large_gap_factor: float = 10.0
    large_shrink: float = 0.6
    #: A candidate whose fitted model widens the pooled validation gap (all validation
    #: samples, the gap the report's headline gives) by more than this fraction of its RMS
    #: is not significant, whatever the per-experiment (geometric) terms say: an effect
    #: that makes the largest gaps worse does not explain the gap, it trades one
    #: experiment's residual for another's. Under the relative significance this is the
    #: one rule on the pooled gap (the pooled significance already asks for a shrink above
    #: the complexity penalty). The same holds for a candidate judged on every experiment
    #: whose own fit (the one a selection carries) widens the round's pooled validation
    #: gap (:func:`~nanostage.diagnosis.select.without_unsupported`). A negative value
    #: turns the rule off.
    max_pooled_widening: float = 0.05
    #: The effect a round names must shrink the gap as measured (the report's headline:
    #: the pooled validation gap of the reading, without the command channel and without
    #: the level-scatter discount the judging uses) by more than its complexity penalty
    #: (:attr:`penalty_base` + :attr:`penalty_per_param` per parameter). Otherwise the
    #: round's pick is not significant and the round picks again: the judging may find an
    #: effect on the discounted, command-weighted gaps, but the report names an effect as
    #: the cause of the gap it gives, and an effect that leaves that gap as it was (or
    #: larger) does not explain it. False turns the rule off.
    measured_shrink_rule: bool = True
    #: A friction-law candidate (:data:`~.loop.FRICTION_MODELS`: `coulomb_viscous`,
    #: `stribeck`, `dahl`, `lugre`, `gms`) replaces the nominal friction law, and every law
    #: is an approximation: another law fitted to a model's friction always takes up part
    #: of the law's form error, whatever else is missing ("friction laws trade off against
    #: each other"). So a friction-law candidate is significant only when it explains at
    #: least this share of the validation gap's mean square (from the judged shrink s:
    #: 1 − (1 − s)², the geometric shrink under the relative significance; 0.5 means
    #: s ≥ 29.3 %): most of the gap, not a partial fit of the form error. With less, the
    #: report names it among the best partial explanations of an unexplained gap. An added
    #: effect (an offset, a compliance) has no such standing fit to take up and keeps the
    #: complexity penalty alone. 0 turns the rule off.
    friction_model_share: float = 0.5
    #: The marks of the friction's speed dependence (:data:`~.loop.SPEED_MARKS`: the steady
    #: ramp command at rest and its rise with speed) that the model before misses by more
    #: than three standard errors are the traces' own evidence for a friction law, which a
    #: law's presliding form error does not reach.
    #: A friction law whose own fit removes at least this share of their χ²
    #: (:func:`~.loop.speed_mark_support`) is not held back by :attr:`friction_model_share`.
    #: 0 turns the exemption off.
    speed_mark_share: float = 0.5
    #: Use the measured command (``command_v``) as a second channel of the gap when every
    #: experiment has one: fits, noise floors and significance then weigh the command gap
    #: against the position gap by each channel's noise floor (:func:`~.loop.command_weight`).
    #: Friction-law effects (Stribeck, dwell-dependent breakaway, presliding shape) move the
    #: encoder reading of a stiff loop by a fraction of a count but its command clearly.
    command_channel: bool = True
    #: The run-to-run scatter of the friction levels (relative, 1σ; e.g. 0.02 for 2 %), for
    #: experiments without repeats; default 1 % (:data:`DEFAULT_LEVEL_SCATTER`), 0 leaves
    #: it out. With it, each experiment's gap allows for one level draw of its own: its
    #: component along the direction a level change moves it is discounted by the scatter
    #: (:mod:`~nanostage.diagnosis.scatter`), so a long saturated step, whose position
    #: error a 1 % level change makes add up over the whole move, no longer outweighs the
    #: holds, ramps and micro-steps that carry the effects' marks. Measured once on fresh
    #: seeds with 0.01 (docs/benchmarks.md): independent family 4/7 and 2/7 first picks
    #: against 2/7 and 2/7 without it (seeds 92, 95), own family 6/7 with and without;
    #: the EMPS data give the same selections and gaps with it and without. On by default
    #: since the runs of docs/benchmarks.md (*The run-to-run scatter by default*).
    level_scatter: float = DEFAULT_LEVEL_SCATTER
    #: How a round orders its candidates, and so which significant one it selects and
    #: which it calls tied (:mod:`~nanostage.diagnosis.select`): ``"relative"``, by the
    #: mean over the validation experiments of log(mean-square gap), every experiment
    #: counting by the factor a candidate cuts its own gap; ``"pooled"``, by the pooled
    #: RMS gap, where the loudest experiment (a long step) decides. Fixed before scoring
    #: from the misses of the consumed benchmark seeds, where the truth was often second
    #: by the pooled gap and first on the dwells, micro-steps and ramps; scored once on
    #: fresh seeds (docs/benchmarks.md: independent 4/14, own 11/14 first picks, within
    #: the noise of the pooled ranking's 33 % and 76 %).
    ranking: str = "relative"
    #: How a candidate is judged significant (:mod:`~nanostage.diagnosis.select`):
    #: ``"relative"``, in the ranking's terms: per validation experiment the log ratio of
    #: the mean-square gaps before and after (each clamped at that experiment's noise
    #: floor), the bootstrap over the validation experiments, and the geometric shrink
    #: against the complexity penalty; ``"pooled"``, the pooled gap (the bootstrap over
    #: validation moves, the pooled shrink, the noise-and-refit gain). Chosen, before
    #: scoring, for a lag the calibration had absorbed (a consumed case): refitted jointly
    #: it found the truth's 474 Hz within 1 Hz and cut the gaps of the quiet validation
    #: experiments two- to threefold, but the pooled gap rose because the 1 mm step,
    #: dominated by a run-to-run friction level draw, got worse. Scored once on fresh seeds
    #: (docs/benchmarks.md): independent family 2/7, own family 6/7 first picks, no false
    #: alarm; no better than the pooled rules' earlier scores by what seven cases show.
    significance: str = "relative"
    forward_rounds: int = 3
    forward_top: int = 8
    refine_top: int = 4
    #: Also refine the best-screened friction-model candidate outside the best
    #: :attr:`refine_top`: a friction model replaces the table friction, so its screening
    #: starts are not near the model before, and its screened gap says less about its best
    #: fit than another candidate's (on a presliding case of seed 19 LuGre was among the
    #: best four, the GMS candidate screened sixth, 108 nm, and refitted alone at 47 nm).
    refine_best_friction_model: bool = True
    #: Also refine the alias of a refined offset force or asymmetric friction
    #: (:data:`~.loop.BIAS_ALIASES`). Both shift the sliding force by direction; they
    #: differ at rest and at breakaway only, and screened with the nominal held a
    #: two-sided asymmetry can rank far below the one-parameter offset on small validation
    #: gaps: on a consumed asymmetry case the two screened alike on the pooled gap (14 %)
    #: but the asymmetry 12th by geometric shrink, and the offset was selected unrefuted
    #: (87 %), while refitted alone the asymmetry cut the gap by 91–96 %. Costs one more
    #: refit where one of them is refined.
    refine_bias_aliases: bool = True
    #: Also refine every candidate of the lag family (:data:`~.loop.LAG_FAMILY`: backlash,
    #: the delays, drive compliance, amplifier lag) when the model before has a free
    #: parameter at its bound (:func:`~nanostage.diagnosis.fit.at_bounds`). Such a
    #: calibration has bent the model to stand in for something it lacks; screened with
    #: it held, a lag effect cannot undo the bend and ranks low (an amplifier lag screened
    #: 12th of 17 on a consumed case, and its joint refit found the truth's bandwidth).
    #: Costs one full refit per family member on those cases only.
    refine_lag_family_at_bounds: bool = True
    #: Also refine the candidates that make a mark of the traces the model before, as
    #: calibrated, misses by more than three standard errors
    #: (:func:`~nanostage.diagnosis.signatures.misses`, :func:`~.loop.mark_effects`): the
    #: offset force and the friction asymmetry for the mean command of the two directions
    #: (on ramps or at rest), the dwell-dependent friction for the rise of breakaway with
    #: rest, the lag family for every other mark (the limit cycle in holds, the ramps'
    #: command level and slope, the split of the rest command, the lost motion at
    #: reversals). A calibration bent to stand in for a lag shows there before any
    #: parameter reaches a bound: on a consumed amplifier-lag case the calibrated friction
    #: fell until the steps' slews matched, the ramps' command level fell 70 standard
    #: errors short, the held screening left the lag outside the refitted five, and its
    #: joint fit cut the validation gap by 62 %. A missed bias screened with a calibration
    #: held that had taken up what it could of it: on a consumed asymmetry case the
    #: asymmetry screened 12th of 17 and was not refitted, while the lag family, which
    #: cannot move a bias, was. On the independent family the ramps' command is missed in
    #: nearly every case, so this costs up to five more full refits there; on the own
    #: family (no command) it acts where a limit cycle is missed (backlash and delay
    #: cases).
    refine_on_missed_marks: bool = True
    #: The lag family's extra refits (at bounds, on missed marks) leave out a member whose
    #: screened pooled validation gap is more than this many times the model before's
    #: (:func:`~nanostage.diagnosis.loop.hopeless_lag_refits`; ``math.inf`` refits every
    #: one). Those refits undo a calibration bent to stand in for a lag, which costs a lag
    #: candidate tens of per cent in screening, not a factor of three. On six consumed
    #: independent cases screened again (no effect, amplifier lag, compliance, offset,
    #: asymmetry, dwell) the hidden lags screened at a smaller gap than before, backlash,
    #: compliance and amplifier lag within 2.2 times it everywhere, and the delays (a
    #: one-sample delay added to a loop without one) at 1.6–1.8 times on one case and 3.5
    #: to 60 times on the others; on the offset case the delays, refitted at 6.6–7 times,
    #: cost about a fifth of a 396 s diagnosis (their refits and cross-judging).
    lag_refit_max_gap_ratio: float = 3.0
    #: Break a tie by the Occam factor (:func:`log_occam_factor`): among the significant
    #: candidates the validation data cannot tell from the best (:func:`indistinguishable`),
    #: select the one whose own parameters the data pin down most within their bounds (the
    #: Laplace approximation of the Bayesian evidence with uniform priors on the bounds; the
    #: likelihoods count as equal in a tie). Off: the smallest validation gap, a difference
    #: within the noise. Measured on the stored reports of seven benchmark seeds (first
    #: selections, offline, in-sample): 19 picks turned right, 4 wrong; on two seeds drawn
    #: afterwards (22, 23) top-1 97.6 % and 95.2 % against 90.5 % and 88.1 % without it.
    occam_tie_break: bool = True
    #: Narrow a tie by the traces' signatures first (:mod:`~nanostage.diagnosis.signatures`:
    #: limit cycles in holds, the command at rest and on ramps per direction, breakaway
    #: against rest): the tied candidates whose simulated signature lies within this χ² of
    #: the closest one to the measured stay, and the Occam factor decides among them. Only
    #: the marks the tied effects make count (:func:`~nanostage.diagnosis.signatures.
    #: effect_marks`: a feature some tied model moves beyond 3 standard errors against
    #: itself with its effect taken out); a feature none moves differs between them only
    #: by each refit's compromise on the shared nominal parameters. Each feature counts in
    #: units of the closest tied model's miss of it where that exceeds its errors
    #: (:func:`~nanostage.diagnosis.signatures.tie_chi_squares`): a mark every model
    #: misses alike is a shared model error, not a difference between them. The
    #: default 9.21 = 2·ln 100, a likelihood ratio of 100 ("decisive" on Jeffreys' scale):
    #: a tie the gap cannot break is broken only by a clear mark. 0 turns it off.
    signature_margin: float = 9.21
    #: Significant candidates of a round whose free values restart the model before
    #: (refitting alone), the best first; None: every significant one, ≤ 0: none. A refit
    #: becomes the baseline if it fits the training experiments better and predicts the
    #: validation experiments no worse (docs/diagnosis.md, *Refitting alone*). With the
    #: best two only (an earlier default), a third significant candidate could be
    #: selected by the tie-break without its control: on the speed bench's delay case,
    #: refitted friction models ranked ahead of the drive compliance whose free values had
    #: restarted the delay model from 511 to 401 nm, and the compliance was selected as a
    #: second effect.
    refit_control_top: int | None = None
    #: Screen each candidate with only its own parameters free, the free nominal parameters
    #: held at the model before's fitted (warm) values: a finite-difference Jacobian then
    #: costs (own parameters + 1) simulation batches instead of (free nominal + own + 1),
    #: and a delay is judged at its best setting without a fit. The screening only ranks
    #: the candidates: the best :attr:`refine_top` (and the best friction model) are
    #: refitted with every free parameter as before, a winner known from its screening
    #: only is refitted before it is selected, and the refit control restarts from the
    #: refitted candidates only (a held candidate's free values are the model before's).
    #: Measured with and without on the same cases (development seeds, shared machine):
    #: the same selection and the same validation shrink to four digits on own family
    #: seed 3, cases 0–7, and independent seeds 10103 (no effect), 10101 (amplifier lag),
    #: 10100 (backlash); on 10102 the drive compliance, missed with the free parameters
    #: fitted in screening, was found (shrink 20.9 %; its second round took 54 340
    #: simulations instead of 47 373). With 9 free nominal parameters (independent family)
    #: it runs fewer simulations otherwise: 37 564 instead of 44 920 on the no-effect case, 44 120
    #: instead of 53 196 on the amplifier case, 57 628 instead of 62 380 on the backlash
    #: case (the screening's fell from 26 248 to 11 776, the
    #: refinement's rose from 28 000 to 37 516: it no longer finds its screening's fits in
    #: the cache). With 3 (own family) there is little to save: from 17 % fewer (offset
    #: force, 25 972 instead of 31 125) to 10 % more (lead-periodic friction, asymmetry).
    screen_holds_nominal: bool = True
    #: With :attr:`screen_holds_nominal`, let the held free nominal parameters move
    #: linearly in screening (variable projection): each candidate is fitted to the part of
    #: the training gap that the free parameters' Jacobian at the model before (computed
    #: once per round and fold, ``free + 1`` simulation batches, kept by the cache) cannot
    #: take up, and its model is then the held one moved by the Gauss–Newton step of the
    #: free parameters (clipped to their bounds; kept only when it lowers the training
    #: gap). A calibration bent to stand in for a missing effect is then undone to first
    #: order at screening cost, so the candidate that made it ranks by what it explains
    #: with the calibration unbent. Off by default: measured on consumed cases only
    #: (docs/diagnosis.md, *Screening with the nominal free to move linearly*).
    screen_moves_nominal: bool = False
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
    threads: int = 0
    #: Folds of the final cross-fit over the validation experiments (report ``crossfit``;
    #: 0 turns it off): each validation experiment judged by the nominal and the selected
    #: model refitted on all the other experiments.
    crossfit_folds: int = 3
    #: Folds of the cross-judging of each round's refitted candidates (≤ 1: off; only with
    #: one train/validate split): every experiment, training ones included, is held out
    #: once, the model before and each refitted candidate are refitted locally on the
    #: others, and the round selects by the same rules over all experiments instead of the
    #: validation ones alone (:func:`~nanostage.diagnosis.loop._cross_judge`).
    cross_judge_folds: int = 3
    #: Candidates fitted at once within a round (Python threads; each fit's simulations
    #: still run as batches on ``threads`` threads). The results do not depend on it.
    parallel_candidates: int = 2
    #: Memory for simulations kept for reuse within one diagnosis (:class:`SimulationCache`),
    #: MB; 0 turns the reuse off. The results do not depend on it: a candidate's refit
    #: repeats its screening's scan and local fits exactly, and these are looked up instead
    #: of simulated again.
    simulation_cache_mb: float = 512.0

    def penalty(self, k_params: int) -> float:
        """The complexity penalty of a candidate with ``k_params`` parameters: the shrink
        it must exceed (:attr:`penalty_base` + :attr:`penalty_per_param` per parameter)."""
        return self.penalty_base + self.penalty_per_param * k_params


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


def print_progress(msg: str, enabled: bool) -> None:
    if enabled:
        # One write of the whole line: a signal handled between the text and its newline
        # (print writes them separately) would glue the next message to this line.
        sys.stderr.write(msg + "\n")
        sys.stderr.flush()


@dataclass(slots=True)
class PhaseClock:
    """Where a diagnosis spends its time: the wall time and the simulations run between
    one :meth:`lap` and the next, per phase and round (a phase lapped again in the same
    round adds to its entry). ``simulated``: the number of simulations run so far (the
    diagnosis's :attr:`~.objective.SimulationCache.misses`), or None without a count
    (then each entry's ``simulated`` is None). Laps are taken on one thread between the
    phases, so the counts of concurrent fits within a phase all fall in that phase."""

    simulated: Callable[[], int] | None = None
    #: The wall clock, s.
    now: Callable[[], float] = time.perf_counter
    entries: list[dict[str, Any]] = field(default_factory=list)
    _time: float = 0.0
    _count: int = 0

    def __post_init__(self) -> None:
        self._time = self.now()
        self._count = self.simulated() if self.simulated else 0

    def lap(self, phase: str, round_: int | None = None) -> None:
        """Charge the time and simulations since the last lap to ``phase`` (of round
        ``round_``, 1-based; None: not part of a round)."""
        now = self.now()
        count = self.simulated() if self.simulated else 0
        seconds, sims = now - self._time, count - self._count
        self._time, self._count = now, count
        for e in self.entries:
            if e["phase"] == phase and e["round"] == round_:
                e["seconds"] += seconds
                if e["simulated"] is not None:
                    e["simulated"] += sims
                return
        self.entries.append(
            {
                "phase": phase,
                "round": round_,
                "seconds": seconds,
                "simulated": sims if self.simulated else None,
            }
        )


def phase_totals(entries: Sequence[Mapping[str, Any]]) -> dict[str, float]:
    """Seconds per phase summed over the rounds of :attr:`PhaseClock.entries`, in the order
    the phases first came."""
    out: dict[str, float] = {}
    for e in entries:
        out[str(e["phase"])] = out.get(str(e["phase"]), 0.0) + float(e["seconds"])
    return out
