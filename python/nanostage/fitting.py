"""The fitting toolkit shared by friction identification (:mod:`nanostage.friction_fit`) and
the gap diagnosis (:mod:`nanostage.diagnosis`).

- :class:`Param`: a fitted parameter with its bounds and start value, and the normalised
  coordinate (linear or logarithmic between the bounds) both fitters search in.
- :func:`information_criteria`: AIC and BIC of a least-squares fit.
- :func:`simplest_of_ties`: the model choice both make once the candidates the data cannot
  tell from the best are known: the simplest of them.
- The friction-model constructors both catalogues build their models with
  (:func:`static_map`, :func:`lugre_model`, :func:`harmonic`): a static map or a LuGre model from a
  Coulomb force and the *static excess* ``Fs − Fc ≥ 0`` (so that every parameter box is a
  valid model), a position harmonic from its cos/sin amplitudes.

What the two fitters do not share, and why, is in docs/architecture.md (one fitting
toolkit).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any, TypeVar

from .effects import LuGre, StaticFrictionMap

__all__ = [
    "Param",
    "harmonic",
    "information_criteria",
    "lugre_model",
    "simplest_of_ties",
    "static_map",
]

T = TypeVar("T")


@dataclass(frozen=True, slots=True, kw_only=True)
class Param:
    """One fitted parameter: SI name (unit suffix), unit, bounds, start value, and whether it
    is fitted in log space (between the bounds)."""

    name: str
    unit: str
    lower: float
    upper: float
    initial: float
    log: bool = False
    #: What the parameter is (for tables), empty if the name says it.
    description: str = ""
    #: The value at which the effect the parameter sizes is absent (an offset of 0 N, an
    #: asymmetry of 0, the nominal voltage limit), for the test that a fitted effect differs
    #: from none; None where no such value lies inside a linear range (a log-scaled size,
    #: whose absence lies beyond its lower bound, or a parameter of a friction law).
    null: float | None = None

    def __post_init__(self) -> None:
        if self.null is not None and (self.log or not self.lower <= self.null <= self.upper):
            raise ValueError(
                f"Param {self.name}: null = {self.null} is invalid: expected a linear "
                f"parameter with its null within [{self.lower}, {self.upper}]"
            )

    def to_unit(self, value: float) -> float:
        """Physical value → normalised coordinate in [0, 1]."""
        if self.log:
            return (math.log(value) - math.log(self.lower)) / (
                math.log(self.upper) - math.log(self.lower)
            )
        return (value - self.lower) / (self.upper - self.lower)

    def from_unit(self, u: float) -> float:
        """Normalised coordinate → physical value."""
        u = min(max(u, 0.0), 1.0)
        if self.log:
            return math.exp(
                math.log(self.lower) + u * (math.log(self.upper) - math.log(self.lower))
            )
        return self.lower + u * (self.upper - self.lower)


def information_criteria(rss: float, n: int, p: int) -> tuple[float, float]:
    """``(AIC, BIC)`` of a least-squares fit of ``p`` parameters to ``n`` residuals with
    residual sum of squares ``rss``: ``n·ln(RSS/n) + 2p`` and ``n·ln(RSS/n) + p·ln n`` (the
    Gaussian log-likelihood up to a constant; ``RSS/n`` floored at 1e-300)."""
    ll = n * math.log(max(rss / n, 1e-300))
    return ll + 2 * p, ll + p * math.log(n)


def simplest_of_ties(
    ranked: Iterable[T], tied: Callable[[T], bool], complexity: Callable[[T], Any]
) -> T:
    """The simplest candidate the data cannot tell from the best: among the ``ranked``
    candidates (best first) for which ``tied`` holds, the one of least ``complexity`` (the
    first in rank order when equal). ``tied`` must hold for at least one (the best)."""
    return min((c for c in ranked if tied(c)), key=complexity)


def static_map(
    fc: float,
    dfs: float,
    fv: float,
    vs: float = 1e-3,
    delta: float = 2.0,
    asym: float = 0.0,
    lag_s: float | None = None,
) -> StaticFrictionMap:
    """A static friction map from the Coulomb force ``fc`` and the static excess ``dfs``
    (``Fs = fc + dfs``), viscous coefficient ``fv``, Stribeck velocity ``vs`` and shape
    ``delta``, direction asymmetry ``asym`` and frictional-memory lag ``lag_s``."""
    return StaticFrictionMap(
        static_force_n=fc + dfs,
        coulomb_force_n=fc,
        viscous_n_s_per_m=fv,
        stribeck_velocity_m_per_s=vs,
        stribeck_exponent=delta,
        asymmetry=asym,
        memory_lag_s=lag_s,
    )


def lugre_model(
    *,
    stiffness_n_per_m: float,
    damping_n_s_per_m: float,
    viscous_n_s_per_m: float,
    coulomb_force_n: float,
    static_excess_n: float,
    stribeck_velocity_m_per_s: float,
) -> LuGre:
    """A LuGre model from the Coulomb force and the static excess
    (``Fs = coulomb_force_n + static_excess_n``)."""
    return LuGre(
        stiffness_n_per_m=stiffness_n_per_m,
        damping_n_s_per_m=damping_n_s_per_m,
        viscous_n_s_per_m=viscous_n_s_per_m,
        coulomb_force_n=coulomb_force_n,
        static_force_n=coulomb_force_n + static_excess_n,
        stribeck_velocity_m_per_s=stribeck_velocity_m_per_s,
    )


def harmonic(kappa: float, c: float, s: float) -> tuple[float, float, float]:
    """``c·cos κx + s·sin κx`` as a position-friction term ``(amplitude, κ, phase)``:
    ``a·cos(κx + φ)`` with ``a = hypot(c, s)``, ``φ = atan2(−s, c)``."""
    return (math.hypot(c, s), kappa, math.atan2(-s, c))
