"""Run-to-run friction scatter in the gap: how much of a move no model can predict.

A real axis does not run at the same friction level twice: from one run to the next the
levels (static and Coulomb, on the motor and the table) wander by a few per cent (lubricant
film, temperature, wear). In a stiff position loop that scatter hides in holds, but where
the loop is open (the amplifier at its rail during a long step) a level that is 1 % off
changes the slew speed, and the position error adds up over the whole move: on a 1 mm step
of the seed axis, a 3 % level change moves the reading by about 0.5 µm RMS and the command
by 0.1 V. Repeated experiments measure that scatter (:func:`~.objective.floors_m`); without
repeats the noise floor is the sensor's alone, a hundred times smaller, and the gap of a
single long step can decide between candidates on what is noise.

With :attr:`~.settings.DiagnosisSettings.level_scatter` ``σ`` (the relative run-to-run
level scatter, 1σ, which the user knows from repeated runs of the machine or assumes), this
module makes each experiment's gap allow for one level draw of its own:

1. **Level sensitivity.** The calibrated model is simulated again with every friction level
   raised by :data:`LEVEL_STEP` (:func:`with_friction_level`: the core's level factor, the
   same one its stochastic friction draws per run); ``J(t)`` is the change of the reading
   and of the command per unit of relative level.
2. **Level direction.** In an experiment's gap ``r`` (position samples, then the weighted
   command samples where the gap has the command) one run's level moves the trace along
   ``u = J`` (stacked the same way), by ``δ·u`` with ``δ`` drawn once per run. The gap's
   covariance is then ``f²·I + σ²·u·uᵀ`` (``f`` the experiment's floor), not the sensor's
   ``f²·I`` alone: the scatter moves all the samples of a run together, along one
   direction. Whitening by it (Sherman–Morrison) keeps every component of ``r`` but the
   one along ``û = u/|u|``, which it keeps by ``1/√(1 + s²)``, ``s = σ·|u|/f``
   (:func:`discount_level`). A long saturated step, whose slew a 1 % level change moves by
   many floors, no longer decides on what one run's level does; what an effect does to
   the same slew apart from a level change still counts in full. Experiments of a kind
   with repeats are left as they are: their floor already holds the scatter.

The directions are fixed once per diagnosis (from the calibrated nominal model), so every
fit stays a least-squares problem and every judgement (validation gap, significance,
bootstrap) uses the same whitened gaps. The report's gaps (before, after, per segment) stay
as measured, in metres.

Estimating ``σ`` from the experiments themselves (each experiment's gap projected on its
``J``) was tried and does not work sample by sample: where stick-slip makes the response
chaotic, a 1 % level change moves the command by ten times its mean change, and model
errors project on ``J`` as much as the scatter does.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from ..config import System
from ..effects import PositionFriction
from ..experiment import Experiment
from .objective import (
    SimulationCache,
    repeat_pairs,
    simulate_readings_and_commands,
)
from .settings import FloatArray

__all__ = [
    "LEVEL_STEP",
    "MAX_LEVEL_SCATTER",
    "LevelScatter",
    "discount_level",
    "level_floors",
    "level_scatter_directions",
    "level_sensitivities",
    "with_friction_level",
]

#: The relative raise of every friction level that measures the level sensitivity.
LEVEL_STEP = 0.01
#: Samples the level sensitivity is averaged over (:func:`_smoothed`): where stick-slip
#: makes the response chaotic, a 1 % level change shifts the cycles' phase and moves the
#: command sample by sample ten times as much as its mean, which is no scatter of the mean.
SMOOTHING_SAMPLES = 25
#: The largest scatter the estimate reports (a relative level, 1σ): beyond it the
#: experiments' gaps are not scatter but a model error, and weighting them away would hide
#: it.
MAX_LEVEL_SCATTER = 0.2
#: A wavenumber so small that ``cos(κ·x)`` is exactly 1 in double precision over any travel
#: (κ·x < 1e-8 rad for |x| < 10 m): a position modulation with it is a constant factor.
_FLAT_RAD_PER_M = 1e-9


def with_friction_level(system: System, factor: float) -> System:
    """``system`` with every friction level (static and Coulomb, of the table law and of the
    motor map; not the viscous terms) times ``factor`` in [1, 1.9]: a constant position
    modulation of both sides, which multiplies the levels exactly as the core's per-run
    level factor does."""
    if not 1.0 <= factor <= 1.9:
        raise ValueError(f"factor = {factor!r} is invalid: expected a level factor in [1, 1.9]")
    if factor == 1.0:
        return system
    flat = ((factor - 1.0, _FLAT_RAD_PER_M, 0.0),)
    has_motor = getattr(system.plant, "motor_friction", None) is not None
    sides = ("table", "motor") if has_motor else ("table",)
    extra = tuple(PositionFriction(side=s, terms=flat) for s in sides)  # type: ignore[arg-type]
    return replace(
        system,
        effects=replace(system.effects, position_friction=system.effects.position_friction + extra),
    )


@dataclass(frozen=True, slots=True, kw_only=True)
class LevelScatter:
    """How a given run-to-run friction scatter enters a diagnosis's gaps (module doc)."""

    #: ``σ``: the relative level scatter, 1σ.
    spread: float
    #: Per experiment (by name) whose gap a level within the scatter moves: the unit vector
    #: ``û`` of that move in the experiment's gap (the position samples, then the weighted
    #: command samples where the gap stacks the command) and the factor ``1/√(1 + s²)``
    #: by which the gap's component along ``û`` is kept (``s = σ·|u|/f``).
    directions: Mapping[str, tuple[FloatArray, float]] = field(default_factory=dict)
    #: ``s`` of each experiment in :attr:`directions`: how many noise floors a level change
    #: of ``σ`` moves its gap (the length of the move over the floor).
    scatter_floors: Mapping[str, float] = field(default_factory=dict)
    #: Experiments left as they are because their kind is repeated (the floor holds the
    #: scatter already).
    repeated: Sequence[str] = ()

    def to_dict(self) -> dict[str, object]:
        return {
            "spread": self.spread,
            "discounted": {
                n: {"scatter_floors": self.scatter_floors[n], "kept": keep}
                for n, (_, keep) in self.directions.items()
            },
            "repeated": list(self.repeated),
        }


def discount_level(gap: FloatArray, direction: tuple[FloatArray, float]) -> FloatArray:
    """``gap`` with its component along the level direction ``û`` kept by the factor
    ``keep`` (``direction = (û, keep)``, :attr:`LevelScatter.directions`): ``r + (keep −
    1)·(û·r)·û``. Times the noise floor ``f``'s inverse it is the gap whitened by the
    covariance ``f²·I + σ²·u·uᵀ`` of the sensor noise and one run-to-run level draw, so its
    sum of squares is the gap's Mahalanobis norm times ``f²``."""
    u, keep = direction
    if len(u) != len(gap):
        raise ValueError(
            f"the level direction has {len(u)} samples, the gap {len(gap)}: they must be "
            "taken from the same channels of the same experiment"
        )
    out: FloatArray = gap + (keep - 1.0) * float(np.dot(u, gap)) * u
    return out


def _smoothed(j: FloatArray) -> FloatArray:
    """``j`` averaged over :data:`SMOOTHING_SAMPLES` samples centred on each (the record's
    ends shrink the window): the level's mean effect, not the phase of a stick-slip cycle
    that a 1 % change shifts."""
    k = SMOOTHING_SAMPLES
    if len(j) < 2 or k <= 1:
        return j
    c = np.concatenate([[0.0], np.cumsum(j)])
    i = np.arange(len(j))
    lo = np.maximum(i - k // 2, 0)
    hi = np.minimum(i + k // 2 + 1, len(j))
    out: FloatArray = (c[hi] - c[lo]) / (hi - lo)
    return out


def level_sensitivities(
    experiments: Sequence[Experiment],
    systems: Mapping[str, System],
    *,
    threads: int = 0,
    cache: SimulationCache | None = None,
) -> dict[str, tuple[FloatArray, FloatArray]]:
    """Each experiment's level sensitivity (by name): the change of the simulated reading
    (m) and of the command (V) per unit of relative friction level, averaged over
    :data:`SMOOTHING_SAMPLES` (:func:`_smoothed`), each experiment simulated with its model
    in ``systems`` (by name) and with every level raised by :data:`LEVEL_STEP`, all in one
    batch. An experiment whose model cannot take the raised level (its position modulation
    full: amplitudes summing to 0.9, or every term in use) is left out."""
    exps, base, raised = [], [], []
    for e in experiments:
        try:
            up = with_friction_level(systems[e.name], 1.0 + LEVEL_STEP)
        except ValueError:
            # A model whose position modulation has no room left (amplitudes summing to
            # 0.9, or every term in use): no sensitivity for it.
            continue
        exps.append(e)
        base.append(systems[e.name])
        raised.append(up)
    simulate = simulate_readings_and_commands if cache is None else cache.simulate
    sims = simulate(base + raised, exps + exps, threads) if exps else []
    n = len(exps)
    return {
        e.name: (
            _smoothed((np.asarray(r1) - np.asarray(r0)) / LEVEL_STEP),
            _smoothed((np.asarray(c1) - np.asarray(c0)) / LEVEL_STEP),
        )
        for e, (r0, c0), (r1, c1) in zip(exps, sims[:n], sims[n:], strict=True)
    }


def level_floors(
    sensitivities: Mapping[str, tuple[FloatArray, FloatArray]],
    floors_m: Mapping[str, float],
    spread: float = 0.01,
) -> dict[str, float]:
    """How far a run-to-run level change of ``spread`` (relative; default 1 %) moves each
    experiment's reading, in units of its noise floor (the RMS over the experiment's
    samples; by name, experiments with a floor > 0 only): above 1, the experiment's gap
    holds scatter that the floor does not count unless repeats measured it."""
    return {
        n: float(np.sqrt(np.mean((spread * jp) ** 2))) / floors_m[n]
        for n, (jp, _) in sensitivities.items()
        if floors_m.get(n, 0.0) > 0.0 and len(jp)
    }


def level_scatter_directions(
    experiments: Sequence[Experiment],
    sensitivities: Mapping[str, tuple[FloatArray, FloatArray]],
    floors_m: Mapping[str, float],
    command_weights_m_per_v: Mapping[str, float],
    count_m: float,
    spread: float,
) -> LevelScatter:
    """The level directions (module doc) of ``experiments`` for a run-to-run friction level
    scatter ``spread`` (relative, 1σ, in (0, :data:`MAX_LEVEL_SCATTER`]) from their level
    ``sensitivities`` (:func:`level_sensitivities`, by name). ``floors_m``: each
    experiment's position floor, m; ``command_weights_m_per_v``: the weight of its command
    gap in its gap (:func:`~.loop.command_weights`; missing or 0: the gap has no command
    samples). An experiment without a sensitivity, or one that a level change does not
    move, is left as it is."""
    if not 0.0 < spread <= MAX_LEVEL_SCATTER:
        raise ValueError(
            f"level_scatter = {spread!r} is invalid: expected a relative friction level "
            f"scatter in (0, {MAX_LEVEL_SCATTER}]"
        )
    exps = list(experiments)
    repeated = {n for a, b in repeat_pairs(exps, count_m) for n in (a.name, b.name)}
    directions: dict[str, tuple[FloatArray, float]] = {}
    moved: dict[str, float] = {}
    for e in exps:
        fp = floors_m.get(e.name, 0.0)
        if e.name in repeated or fp <= 0.0 or e.name not in sensitivities:
            continue
        jp, jc = sensitivities[e.name]
        cw = command_weights_m_per_v.get(e.name, 0.0)
        u = np.concatenate([jp, cw * jc]) if cw > 0.0 and e.command_v is not None else jp
        norm = float(np.linalg.norm(u))
        if not norm > 0.0:
            continue
        s = spread * norm / fp
        directions[e.name] = (u / norm, 1.0 / math.sqrt(1.0 + s * s))
        moved[e.name] = s
    return LevelScatter(
        spread=spread, directions=directions, scatter_floors=moved, repeated=sorted(repeated)
    )
