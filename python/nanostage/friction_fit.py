"""Friction identification from component data.

Fit a friction model to measured ``(time, displacement, velocity, force)`` records of a
component (a guide, a screw, a whole axis pushed by a force-controlled drive), estimate the
parameters' standard errors, and compare models on held-out data.

The model evaluation is :func:`nanostage.friction.friction_response`: the Rust core drives
the component along the measured motion (linear interpolation of the velocity between
samples, internal states from rest at the first sample) and returns its force. The models
integrate the *velocity* channel; the position enters only through position-dependent
friction (the lead families). Give a velocity consistent with the position
(:meth:`FrictionData.from_position` differentiates the position).

Model families (:data:`MODELS`, by stable name)
    ``coulomb_viscous`` (2), ``stribeck`` (4, Gaussian shape δ = 2), ``stribeck_shape`` (5,
    δ fitted), ``stribeck_asymmetric`` (5, δ = 2, direction asymmetry), ``dahl`` (3),
    ``lugre`` (6), ``stribeck_memory`` (5, frictional memory: the Stribeck term follows the
    velocity lagged by ``memory_lag_s``), ``gms3`` (9) and ``gms6`` (15); :func:`gms_family`
    makes a GMS with any number of elements in [1, 8], :func:`lead_family` a Stribeck map
    modulated with a given screw lead (``stribeck_lead<h>``, cos/sin amplitude per harmonic).
    Rising static friction with dwell time is not identifiable here: along a prescribed
    motion a static map's force at rest is set by the rest of the system, so the breakaway
    force never enters the record's model force (it needs a force-driven breakaway test). Each
    family lists its parameters (SI names and units),
    default bounds scaled from the data (:class:`DataScales`) and a ``build(theta)`` that
    returns the component. Scale parameters (stiffnesses, Stribeck velocity, LuGre damping)
    are fitted in log space; forces and coefficients that may be 0 are fitted linearly. The
    static force is fitted as ``static_excess_n = Fs − Fc ≥ 0`` so that every parameter box
    is a valid model.

Fit (:func:`fit_friction`)
    The last ``holdout`` fraction of the record (contiguous in time) is held out; the first
    part is fitted. Residual ``(F_model − F_measured)/scale`` on the fit part, ``scale`` the
    RMS measured force. ``scipy.optimize.least_squares`` (``trf``, bounded) runs in the
    unit box ``u ∈ [0, 1]^p`` mapped affinely onto the (log) parameter bounds, from
    ``n_starts`` starts: a data-driven guess (a linear Coulomb + viscous fit of the moving
    samples, mid-range values for the rest) and ``n_starts − 1`` Latin-hypercube points
    (``scipy.stats.qmc``, seeded). Jacobians are forward differences (step 1e-5 of the
    parameter range). The best start wins. The held-out error simulates the whole record, so
    the held-out part starts from the fitted model's own state.

Standard errors
    From the central-difference Jacobian ``J`` at the optimum (step 1e-4 of each range):
    ``cov = s²·(JᵀJ)⁺`` with ``s² = RSS/(n_fit − p_free)``, the pseudo-inverse by SVD of
    the unit-box Jacobian, mapped to physical units (log parameters by the delta method,
    ``se(θ) = θ·se(ln θ)``). They assume independent, equal-variance force errors: with
    model error or coloured noise they are optimistic. Status per parameter: ``"ok"``;
    ``"at_bound"`` (within 1e-6 of the range from a bound: held fixed, se NaN);
    ``"non_identifiable"`` (se = inf): it lies in a numerically null direction of ``J``
    (singular value below 1e-10 of the largest), or its standard error exceeds half its
    bound range, so the data cannot place it within its bounds.

Comparison (:func:`compare_models`)
    Every model is fitted with the same split and seed; they are ranked by held-out RMS.
    ``rule="one_se"`` (default) selects the model with the fewest parameters whose held-out
    RMS is within one standard error of the smallest (the standard error of the RMS from
    batch means over 20 contiguous blocks of the held-out part, which allows for correlated
    errors); ``rule="bic"`` selects the smallest BIC on the fit part (used automatically
    when nothing is held out). AIC/BIC: ``n·ln(RSS/n) + 2p`` / ``+ p·ln n`` on the fit part.

The equations of each model are in ``/work/shared/docs/DOMAIN.md`` §3; usage, default
bounds, results on synthetic data and costs are in ``docs/friction_fit.md``.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import numpy.typing as npt
from scipy.optimize import least_squares
from scipy.stats import qmc

from ._core import ConfigError, SimulationError
from .blas import single_threaded_blas
from .config import DahlFriction, IntegratorOptions
from .effects import Gms, PositionFriction, StaticFrictionMap
from .fitting import (
    Param,
    harmonic,
    information_criteria,
    lugre_model,
    simplest_of_ties,
    static_map,
)
from .friction import FrictionModel, friction_response

__all__ = [
    "DEFAULT_COMPARISON",
    "MODELS",
    "DataScales",
    "FrictionData",
    "FrictionFit",
    "ModelComparison",
    "ModelFamily",
    "Parameter",
    "ParameterStatus",
    "StartResult",
    "compare_models",
    "fit_friction",
    "gms_family",
    "lead_family",
]

FloatArray = npt.NDArray[np.float64]
ParameterStatus = Literal["ok", "at_bound", "non_identifiable"]
Bounds = Mapping[str, tuple[float, float]]
Progress = Callable[[int, int], None]

#: Forward-difference step of the optimiser's Jacobian, as a fraction of each parameter range.
_STEP_OPT = 1e-5
#: Central-difference step of the covariance Jacobian, as a fraction of each parameter range.
_STEP_COV = 1e-4
#: Distance (fraction of the range) under which an estimate counts as on its bound.
_AT_BOUND = 1e-6
#: Relative singular value (unit-box Jacobian) under which a direction is numerically null.
_RCOND = 1e-10
#: Share of a parameter in the null directions that flags it as non-identifiable.
_NULL_SHARE = 0.1
#: Standard error, as a fraction of the bound range, above which a parameter is flagged
#: non-identifiable (the data cannot place it within its bounds).
_MAX_SE_U = 0.5
#: Residual (in units of the force scale) given to parameters whose simulation fails.
_PENALTY = 1e3


def _as_array(name: str, a: npt.ArrayLike) -> FloatArray:
    try:
        out = np.array(a, dtype=np.float64, copy=True)
    except (TypeError, ValueError) as e:
        raise ConfigError(f"{name} is invalid: expected a 1-D array of numbers ({e})") from e
    if out.ndim != 1:
        raise ConfigError(f"{name} = array of shape {out.shape} is invalid: expected a 1-D array")
    bad = np.flatnonzero(~np.isfinite(out))
    if bad.size:
        k = int(bad[0])
        raise ConfigError(f"{name}[{k}] = {out[k]} is invalid: expected a finite number")
    out.setflags(write=False)
    return out


@dataclass(frozen=True, slots=True, eq=False, init=False)
class FrictionData:
    """A measured friction record: one sample per row, SI units.

    Parameters
    ----------
    time_s : (n,) array, s, strictly increasing.
    position_m : (n,) array, m (displacement of the component).
    velocity_m_per_s : (n,) array, m/s (drives the models; see the module docstring).
    force_n : (n,) array, N, the friction force (same sign convention as the models: it
        opposes the motion, ``F > 0`` for ``v > 0`` when sliding).

    The arrays are copied, converted to float64 and made read-only. Raises
    :class:`nanostage.ConfigError` naming the field for wrong shapes or lengths, NaN/inf
    values, a time that does not increase, or fewer than 10 samples.
    """

    time_s: FloatArray
    position_m: FloatArray
    velocity_m_per_s: FloatArray
    force_n: FloatArray

    def __init__(
        self,
        time_s: npt.ArrayLike,
        position_m: npt.ArrayLike,
        velocity_m_per_s: npt.ArrayLike,
        force_n: npt.ArrayLike,
    ) -> None:
        names = ("time_s", "position_m", "velocity_m_per_s", "force_n")
        given = (time_s, position_m, velocity_m_per_s, force_n)
        arrays = [_as_array(n, a) for n, a in zip(names, given, strict=True)]
        for n, a in zip(names, arrays, strict=True):
            object.__setattr__(self, n, a)
        n0 = arrays[0].size
        for n, a in zip(names[1:], arrays[1:], strict=True):
            if a.size != n0:
                raise ConfigError(
                    f"{n} has length {a.size}, which is invalid: expected the length of "
                    f"time_s ({n0})"
                )
        if n0 < 10:
            raise ConfigError(f"time_s has {n0} samples, which is too few: expected ≥ 10")
        dt = np.diff(arrays[0])
        bad = np.flatnonzero(~(dt > 0))
        if bad.size:
            k = int(bad[0]) + 1
            raise ConfigError(
                f"time_s[{k}] = {arrays[0][k]} is invalid: expected strictly greater than "
                f"time_s[{k - 1}] = {arrays[0][k - 1]}"
            )

    @classmethod
    def from_position(
        cls, time_s: npt.ArrayLike, position_m: npt.ArrayLike, force_n: npt.ArrayLike
    ) -> FrictionData:
        """A record whose velocity is the derivative of the position (``numpy.gradient``,
        second order inside, first order at the ends). Smooth a quantised position first."""
        probe = cls(time_s, position_m, np.zeros(np.shape(position_m)), force_n)
        return cls(
            probe.time_s,
            probe.position_m,
            np.gradient(probe.position_m, probe.time_s),
            probe.force_n,
        )

    @property
    def n_samples(self) -> int:
        """Number of samples."""
        return int(self.time_s.size)

    def _slice(self, start: int, stop: int) -> FrictionData:
        return FrictionData(
            self.time_s[start:stop],
            self.position_m[start:stop],
            self.velocity_m_per_s[start:stop],
            self.force_n[start:stop],
        )

    def split(self, fraction: float) -> tuple[FrictionData, FrictionData]:
        """``(fit, held_out)``: the last ``fraction`` of the samples (contiguous in time),
        ``fraction`` in (0, 0.9]; each part keeps ≥ 10 samples. The held-out part, fitted or
        simulated on its own, starts from relaxed states; :func:`fit_friction` instead
        simulates the whole record so that the held-out part continues the fit part."""
        n_fit = _split_index(self.n_samples, fraction, allow_zero=False)
        return self._slice(0, n_fit), self._slice(n_fit, self.n_samples)


def _split_index(n: int, fraction: float, *, allow_zero: bool) -> int:
    lo_ok = fraction >= 0 if allow_zero else fraction > 0
    if not (lo_ok and fraction <= 0.9 and math.isfinite(fraction)):
        want = "[0, 0.9]" if allow_zero else "(0, 0.9]"
        raise ConfigError(f"holdout = {fraction} is invalid: expected a fraction in {want}")
    n_hold = round(fraction * n)
    if fraction > 0 and n_hold < 10:
        raise ConfigError(
            f"holdout = {fraction} is invalid: it holds out {n_hold} of {n} samples; "
            "expected ≥ 10 (use more data or a larger fraction)"
        )
    if n - n_hold < 10:
        raise ConfigError(
            f"holdout = {fraction} is invalid: it leaves {n - n_hold} samples to fit; expected ≥ 10"
        )
    return n - n_hold


@dataclass(frozen=True, slots=True, kw_only=True)
class DataScales:
    """Scales of a record from which the default bounds are set.

    ``travel_m`` and ``step_m`` come from the integrated velocity (what the models see).
    """

    #: Largest |force|, N.
    force_n: float
    #: Largest |velocity|, m/s.
    velocity_m_per_s: float
    #: 10th percentile of the non-zero |velocity|, m/s: the slow end of the excitation.
    slow_velocity_m_per_s: float
    #: Peak-to-peak displacement, m.
    travel_m: float
    #: 10th percentile of the non-zero |displacement per sample|, m: the finest resolved motion.
    step_m: float

    @classmethod
    def from_data(cls, data: FrictionData) -> DataScales:
        """Scales of ``data``. Raises ``ConfigError`` when the record has no motion or no
        force (nothing to identify)."""
        f = float(np.max(np.abs(data.force_n)))
        v = np.abs(data.velocity_m_per_s)
        vmax = float(np.max(v))
        if not f > 0:
            raise ConfigError("force_n is zero everywhere: expected a measured friction force")
        if not vmax > 0:
            raise ConfigError(
                "velocity_m_per_s is zero everywhere: expected a motion that excites friction"
            )
        dx = 0.5 * (data.velocity_m_per_s[1:] + data.velocity_m_per_s[:-1]) * np.diff(data.time_s)
        x = np.concatenate([[0.0], np.cumsum(dx)])
        adx = np.abs(dx[dx != 0])
        travel = float(np.ptp(x))
        step = float(np.percentile(adx, 10)) if adx.size else travel
        return cls(
            force_n=f,
            velocity_m_per_s=vmax,
            slow_velocity_m_per_s=max(float(np.percentile(v[v > 0], 10)), 1e-6 * vmax),
            travel_m=max(travel, 1e-300),
            step_m=max(min(step, travel), 1e-12 * max(travel, 1e-300)),
        )


@dataclass(frozen=True, slots=True)
class Parameter:
    """One fitted parameter of a family: SI name (unit suffix), unit, whether it is fitted in
    log space. Its bounds depend on the record: a fit resolves it into a
    :class:`nanostage.fitting.Param` with the record's bounds and start value."""

    name: str
    unit: str
    log: bool
    description: str


@dataclass(frozen=True, slots=True)
class ModelFamily:
    """A friction model family: its parameters, default bounds and component builder.

    ``builder`` maps the parameter vector (physical values, order of ``parameters``) to a
    component; ``bounds_rule`` gives the default bounds from :class:`DataScales`.
    """

    name: str
    description: str
    parameters: tuple[Parameter, ...]
    builder: Callable[[FloatArray], FrictionModel] = field(repr=False)
    bounds_rule: Callable[[DataScales], dict[str, tuple[float, float]]] = field(repr=False)
    #: Position-dependent modulation of the levels for a parameter vector (None: none).
    position_builder: Callable[[FloatArray], PositionFriction] | None = field(
        default=None, repr=False
    )

    @property
    def parameter_names(self) -> tuple[str, ...]:
        """Parameter names in vector order."""
        return tuple(p.name for p in self.parameters)

    @property
    def n_params(self) -> int:
        """Number of fitted parameters."""
        return len(self.parameters)

    def build(self, theta: Sequence[float] | FloatArray) -> FrictionModel:
        """The component for parameter vector ``theta`` (physical values, SI)."""
        th = np.asarray(theta, dtype=np.float64)
        if th.shape != (self.n_params,):
            raise ConfigError(
                f"theta of shape {th.shape} is invalid for {self.name!r}: expected "
                f"({self.n_params},) in the order {self.parameter_names}"
            )
        return self.builder(th)

    def position(self, theta: Sequence[float] | FloatArray) -> PositionFriction | None:
        """The position-dependent modulation for ``theta`` (None for families without)."""
        if self.position_builder is None:
            return None
        return self.position_builder(np.asarray(theta, dtype=np.float64))

    def default_bounds(self, data: FrictionData | DataScales) -> dict[str, tuple[float, float]]:
        """Default ``{name: (lower, upper)}`` bounds scaled from the data."""
        scales = data if isinstance(data, DataScales) else DataScales.from_data(data)
        return self.bounds_rule(scales)


# ----- parameters and bounds shared by the families ------------------------------------------

_FC = Parameter("coulomb_force_n", "N", False, "Coulomb (sliding) friction force Fc")
_DFS = Parameter("static_excess_n", "N", False, "static minus Coulomb force, Fs − Fc")
_FV = Parameter("viscous_n_s_per_m", "N·s/m", False, "viscous coefficient")
_VS = Parameter("stribeck_velocity_m_per_s", "m/s", True, "Stribeck velocity vs")
_DELTA = Parameter("stribeck_exponent", "1", False, "Stribeck shape exponent δ")
_ASYM = Parameter("asymmetry", "1", False, "direction asymmetry a: F·(1 ± a)")
_SIGMA = Parameter("stiffness_n_per_m", "N/m", True, "presliding (bristle) stiffness σ0")
_DAHL_N = Parameter("exponent", "1", False, "Dahl shape exponent n")
_SIGMA1 = Parameter("damping_n_s_per_m", "N·s/m", True, "LuGre micro-damping σ1")
_LAG = Parameter(
    "memory_lag_s", "s", True, "frictional memory: lag of the Stribeck term behind the velocity"
)
#: Bounds of the memory lag, s (frictional memory is milliseconds to tens of ms).
MEMORY_LAG_BOUNDS_S = (1e-4, 0.1)
#: Bounds of a lead-periodic harmonic's cos/sin amplitude (relative modulation).
LEAD_AMPLITUDE_BOUNDS = (-0.5, 0.5)


def _force_bounds(s: DataScales, n: int = 1) -> tuple[float, float]:
    return (1e-3 * s.force_n / n, 1.5 * s.force_n / n)


def _stiffness_bounds(s: DataScales) -> tuple[float, float]:
    # Presliding length Fc/σ between a tenth of the finest resolved motion and a tenth of
    # the travel.
    lo = min(10 * s.force_n / s.travel_m, 1e11)
    hi = min(10 * s.force_n / s.step_m, 1e12)
    return (lo, max(hi, 10 * lo))


def _common_bounds(s: DataScales) -> dict[str, tuple[float, float]]:
    vs_hi = min(s.velocity_m_per_s, 10.0)
    return {
        _FC.name: _force_bounds(s),
        _DFS.name: (0.0, 1.5 * s.force_n),
        _FV.name: (0.0, 2 * s.force_n / s.velocity_m_per_s),
        _VS.name: (min(s.slow_velocity_m_per_s, 0.1 * vs_hi), vs_hi),
        _DELTA.name: (0.5, 4.0),
        _ASYM.name: (-0.9, 0.9),
        _SIGMA.name: _stiffness_bounds(s),
        _DAHL_N.name: (0.5, 4.0),
        _SIGMA1.name: (
            1e-3 * s.force_n / s.velocity_m_per_s,
            min(s.force_n / s.slow_velocity_m_per_s, 1e7),
        ),
    }


def _family(
    name: str,
    description: str,
    params: tuple[Parameter, ...],
    builder: Callable[[FloatArray], FrictionModel],
) -> ModelFamily:
    names = [p.name for p in params]

    def rule(s: DataScales) -> dict[str, tuple[float, float]]:
        b = _common_bounds(s)
        return {n: b[n] for n in names}

    return ModelFamily(name, description, params, builder, rule)


def _stribeck_memory() -> ModelFamily:
    """Stribeck map whose Stribeck term follows the velocity lagged by ``memory_lag_s``."""
    params = (_FC, _DFS, _VS, _FV, _LAG)

    def rule(s: DataScales) -> dict[str, tuple[float, float]]:
        b = _common_bounds(s)
        return {p.name: b[p.name] for p in params[:4]} | {_LAG.name: MEMORY_LAG_BOUNDS_S}

    return ModelFamily(
        "stribeck_memory",
        "static Stribeck map (δ = 2) with frictional memory (lagged Stribeck term)",
        params,
        lambda th: static_map(_f(th, 0), _f(th, 1), _f(th, 3), _f(th, 2), lag_s=_f(th, 4)),
        rule,
    )


def lead_family(lead_m: float, harmonics: int = 1) -> ModelFamily:
    """Stribeck map (δ = 2) whose levels are modulated along the travel with the screw lead:
    ``1 + Σ_k [c_k·cos(kκx) + s_k·sin(kκx)]``, ``κ = 2π/lead_m``, harmonics ``k = 1..harmonics``
    (1–4). The lead is a design value, not fitted; the ``cos_amplitude[k]``/``sin_amplitude[k]``
    are (relative, in [−0.5, 0.5]). Fit on a record that travels several leads."""
    if not (isinstance(lead_m, float | int) and math.isfinite(lead_m) and lead_m > 0):
        raise ConfigError(f"lead_m = {lead_m!r} is invalid: expected a positive length in m")
    if not (isinstance(harmonics, int) and 1 <= harmonics <= 4):
        raise ConfigError(f"harmonics = {harmonics!r} is invalid: expected an integer in [1, 4]")
    kappa = 2.0 * math.pi / float(lead_m)
    harm = tuple(
        Parameter(f"{part}_amplitude[{k}]", "1", False, f"{part} amplitude of harmonic {k + 1}")
        for k in range(harmonics)
        for part in ("cos", "sin")
    )
    params = (_FC, _DFS, _VS, _FV, *harm)

    def rule(s: DataScales) -> dict[str, tuple[float, float]]:
        b = _common_bounds(s)
        return {p.name: b[p.name] for p in params[:4]} | {
            p.name: LEAD_AMPLITUDE_BOUNDS for p in harm
        }

    def position(th: FloatArray) -> PositionFriction:
        terms = []
        for k in range(harmonics):
            c, sn = float(th[4 + 2 * k]), float(th[5 + 2 * k])
            terms.append(harmonic(kappa * (k + 1), c, sn))
        return PositionFriction(side="table", terms=tuple(terms))

    return ModelFamily(
        f"stribeck_lead{harmonics}",
        f"static Stribeck map (δ = 2) modulated with the lead {lead_m * 1e3:g} mm "
        f"({harmonics} harmonic(s))",
        params,
        lambda th: static_map(_f(th, 0), _f(th, 1), _f(th, 3), _f(th, 2)),
        rule,
        position,
    )


def gms_family(n_elements: int) -> ModelFamily:
    """A generalized Maxwell-slip family with ``n_elements`` elements (1–8).

    Parameters: ``slip_force_n[i]`` (element ``i`` slips at ``slip_force_n[i]·s(v)/Fc``,
    so ``Fc = Σ slip_force_n`` and ``weights = slip_force_n/Fc``), ``stiffness_n_per_m[i]``,
    ``static_excess_n``, ``stribeck_velocity_m_per_s``, ``viscous_n_s_per_m``. Elements are
    interchangeable: the fit reports one of the equivalent orderings.
    """
    if not (isinstance(n_elements, int) and 1 <= n_elements <= 8):
        raise ConfigError(f"n_elements = {n_elements!r} is invalid: expected an integer in [1, 8]")
    n = n_elements
    params = (
        tuple(
            Parameter(f"slip_force_n[{i}]", "N", False, f"Coulomb slip force of element {i}")
            for i in range(n)
        )
        + tuple(
            Parameter(f"stiffness_n_per_m[{i}]", "N/m", True, f"stiffness of element {i}")
            for i in range(n)
        )
        + (_DFS, _VS, _FV)
    )

    def build(th: FloatArray) -> FrictionModel:
        w = th[:n]
        fc = float(np.sum(w))
        return Gms(
            stiffness_n_per_m=tuple(float(k) for k in th[n : 2 * n]),
            weights=tuple(float(x) for x in w / fc),
            coulomb_force_n=fc,
            static_force_n=fc + float(th[2 * n]),
            stribeck_velocity_m_per_s=float(th[2 * n + 1]),
            viscous_n_s_per_m=float(th[2 * n + 2]),
        )

    def rule(s: DataScales) -> dict[str, tuple[float, float]]:
        b = _common_bounds(s)
        out = {f"slip_force_n[{i}]": _force_bounds(s, n) for i in range(n)}
        out |= {f"stiffness_n_per_m[{i}]": b[_SIGMA.name] for i in range(n)}
        out |= {p.name: b[p.name] for p in (_DFS, _VS, _FV)}
        return out

    return ModelFamily(
        f"gms{n}",
        f"generalized Maxwell-slip, {n} elements, Gaussian Stribeck slip curve, viscous",
        params,
        build,
        rule,
    )


def _f(th: FloatArray, i: int) -> float:
    return float(th[i])


#: The model families by stable name.
MODELS: Mapping[str, ModelFamily] = {
    f.name: f
    for f in (
        _family(
            "coulomb_viscous",
            "static map F = Fc·sgn v + Fv·v",
            (_FC, _FV),
            lambda th: static_map(_f(th, 0), 0.0, _f(th, 1)),
        ),
        _family(
            "stribeck",
            "static Stribeck map, Gaussian shape (δ = 2)",
            (_FC, _DFS, _VS, _FV),
            lambda th: static_map(_f(th, 0), _f(th, 1), _f(th, 3), _f(th, 2)),
        ),
        _family(
            "stribeck_shape",
            "static Stribeck map with the shape exponent δ fitted",
            (_FC, _DFS, _VS, _DELTA, _FV),
            lambda th: static_map(_f(th, 0), _f(th, 1), _f(th, 4), _f(th, 2), _f(th, 3)),
        ),
        _family(
            "stribeck_asymmetric",
            "static Stribeck map (δ = 2), levels scaled by (1 ± a) with the direction",
            (_FC, _DFS, _VS, _FV, _ASYM),
            lambda th: static_map(_f(th, 0), _f(th, 1), _f(th, 3), _f(th, 2), 2.0, _f(th, 4)),
        ),
        _family(
            "dahl",
            "Dahl: presliding stiffness, Coulomb force, shape exponent",
            (_FC, _SIGMA, _DAHL_N),
            lambda th: DahlFriction(
                coulomb_force_n=_f(th, 0), stiffness_n_per_m=_f(th, 1), exponent=_f(th, 2)
            ),
        ),
        _family(
            "lugre",
            "LuGre: σ0, σ1, σ2 (viscous), Fc, Fs, vs (Gaussian Stribeck)",
            (_SIGMA, _SIGMA1, _FV, _FC, _DFS, _VS),
            lambda th: lugre_model(
                stiffness_n_per_m=_f(th, 0),
                damping_n_s_per_m=_f(th, 1),
                viscous_n_s_per_m=_f(th, 2),
                coulomb_force_n=_f(th, 3),
                static_excess_n=_f(th, 4),
                stribeck_velocity_m_per_s=_f(th, 5),
            ),
        ),
        _stribeck_memory(),
        gms_family(3),
        gms_family(6),
    )
}

#: The models :func:`compare_models` compares by default.
DEFAULT_COMPARISON: tuple[str, ...] = ("coulomb_viscous", "stribeck", "dahl", "lugre", "gms3")


def _resolve_family(model: str | ModelFamily) -> ModelFamily:
    if isinstance(model, ModelFamily):
        return model
    fam = MODELS.get(model)
    if fam is None:
        raise ConfigError(
            f"model = {model!r} is unknown: expected one of {sorted(MODELS)} or a ModelFamily"
        )
    return fam


def _resolve_bounds(
    fam: ModelFamily, scales: DataScales, bounds: Bounds | None
) -> tuple[FloatArray, FloatArray]:
    b = fam.default_bounds(scales)
    for name, pair in (bounds or {}).items():
        if name not in b:
            raise ConfigError(
                f"bounds[{name!r}] is invalid: {fam.name!r} has no such parameter; expected "
                f"one of {list(fam.parameter_names)}"
            )
        try:
            lo, hi = (float(pair[0]), float(pair[1]))
        except (TypeError, ValueError, IndexError) as e:
            raise ConfigError(
                f"bounds[{name!r}] = {pair!r} is invalid: expected (lower, upper)"
            ) from e
        b[name] = (lo, hi)
    lo_a = np.array([b[p.name][0] for p in fam.parameters])
    hi_a = np.array([b[p.name][1] for p in fam.parameters])
    for p, lo, hi in zip(fam.parameters, lo_a, hi_a, strict=True):
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise ConfigError(
                f"bounds[{p.name!r}] = ({lo}, {hi}) is invalid: expected finite lower < upper"
            )
        if p.log and not lo > 0:
            raise ConfigError(
                f"bounds[{p.name!r}] = ({lo}, {hi}) is invalid: {p.name} is fitted in log "
                "space; expected lower > 0"
            )
    return lo_a, hi_a


# ----- results ------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True, kw_only=True)
class StartResult:
    """The outcome of one start of the multi-start search."""

    index: int
    #: Final cost ``½·Σ r²`` in scaled units (see the module docstring).
    cost: float
    #: ``least_squares`` status (> 0: converged by a tolerance; 0: ``max_nfev`` reached).
    status: int
    success: bool
    nfev: int
    message: str


@dataclass(frozen=True, slots=True, kw_only=True)
class FrictionFit:
    """A fitted friction model.

    ``parameters``/``std_errors``/``parameter_status``/``bounds`` are keyed by parameter name
    (SI units in the names), in the family's order. ``covariance`` is in physical units, rows
    and columns in that order, NaN for parameters that are on a bound or not identifiable.
    RMS errors are in N; ``rms_holdout_n`` is NaN when nothing is held out.
    """

    model: str
    parameters: dict[str, float]
    std_errors: dict[str, float]
    parameter_status: dict[str, ParameterStatus]
    bounds: dict[str, tuple[float, float]]
    covariance: FloatArray = field(repr=False)
    n_params: int
    n_fit: int
    n_holdout: int
    rms_fit_n: float
    rms_holdout_n: float
    #: Standard error of ``rms_holdout_n`` (batch means over 20 contiguous blocks), N.
    rms_holdout_se_n: float
    #: ``n·ln(RSS/n) + 2p`` on the fit part (RSS in N²).
    aic: float
    #: ``n·ln(RSS/n) + p·ln n`` on the fit part.
    bic: float
    component: FrictionModel
    #: Model force along the whole record (fit and held-out parts), N.
    predicted_force_n: FloatArray = field(repr=False)
    #: The best start converged (``least_squares`` status > 0).
    success: bool
    n_starts: int
    #: Starts that converged (status > 0).
    n_converged: int
    #: Starts that reached the best cost within 0.1 %.
    n_at_best: int
    starts: tuple[StartResult, ...] = field(repr=False)
    elapsed_s: float
    #: The fitted position-dependent modulation (lead families), else None.
    position_friction: PositionFriction | None = None

    @property
    def identifiable(self) -> bool:
        """No parameter is flagged non-identifiable."""
        return all(s != "non_identifiable" for s in self.parameter_status.values())

    def predict(self, data: FrictionData) -> FloatArray:
        """Force (N) of the fitted component along another record, from relaxed states."""
        return _response(self.component, data, position=self.position_friction)

    def to_markdown(self) -> str:
        """The parameters as a Markdown table (value, standard error, bounds, status)."""
        lines = [
            f"**{self.model}**: fit RMS {self.rms_fit_n:.4g} N, held-out RMS "
            f"{self.rms_holdout_n:.4g} N, {self.n_converged}/{self.n_starts} starts converged",
            "",
            "| parameter | value | std error | lower | upper | status |",
            "|---|---:|---:|---:|---:|---|",
        ]
        for name, value in self.parameters.items():
            lo, hi = self.bounds[name]
            lines.append(
                f"| {name} | {value:.6g} | {self.std_errors[name]:.3g} | {lo:.3g} | {hi:.3g} "
                f"| {self.parameter_status[name]} |"
            )
        return "\n".join(lines)


#: Integrator options for static maps without memory: they have no state to resolve, so the
#: step is not limited (twice as fast as the 1 ms default limit).
_STATIC_OPTIONS = IntegratorOptions(rtol=1e-8, h_max_s=1.0)


def _response(
    component: FrictionModel,
    data: FrictionData,
    n: int | None = None,
    integrator: IntegratorOptions | None = None,
    position: PositionFriction | None = None,
) -> FloatArray:
    """Force of ``component`` along the first ``n`` samples (all by default)."""
    k = data.n_samples if n is None else n
    if (
        integrator is None
        and isinstance(component, StaticFrictionMap)
        and component.memory_lag_s is None
    ):
        integrator = _STATIC_OPTIONS
    return friction_response(
        component,
        data.time_s[:k],
        data.position_m[:k],
        data.velocity_m_per_s[:k],
        position_friction=position,
        integrator=integrator,
    )


# ----- the fit ------------------------------------------------------------------------------


class _Problem:
    """Residuals and Jacobians in the unit box for one family on one record."""

    def __init__(
        self,
        fam: ModelFamily,
        data: FrictionData,
        n_fit: int,
        params: Sequence[Param],
        integrator: IntegratorOptions | None,
    ) -> None:
        self.fam = fam
        self.data = data
        self.n_fit = n_fit
        lo = np.array([q.lower for q in params])
        hi = np.array([q.upper for q in params])
        self.log = np.array([q.log for q in params])
        self.lo_int = np.where(self.log, np.log(np.where(self.log, lo, 1.0)), lo)
        self.hi_int = np.where(self.log, np.log(np.where(self.log, hi, 1.0)), hi)
        self.width = self.hi_int - self.lo_int
        self.integrator = integrator
        f = data.force_n[:n_fit]
        self.f_fit = f
        self.scale = float(np.sqrt(np.mean(f**2))) or 1.0

    def theta(self, u: FloatArray) -> FloatArray:
        q = self.lo_int + np.clip(u, 0.0, 1.0) * self.width
        q[self.log] = np.exp(q[self.log])
        return np.asarray(q, dtype=np.float64)

    def u_of(self, theta: FloatArray) -> FloatArray:
        q = np.where(self.log, np.log(np.maximum(theta, 1e-300)), theta)
        return np.asarray(np.clip((q - self.lo_int) / self.width, 0.0, 1.0), dtype=np.float64)

    def force(self, theta: FloatArray, n: int | None = None) -> FloatArray:
        return _response(
            self.fam.build(theta), self.data, n, self.integrator, self.fam.position(theta)
        )

    def simulate(self, u: FloatArray) -> FloatArray | None:
        try:
            return (self.force(self.theta(u), self.n_fit) - self.f_fit) / self.scale
        except SimulationError:
            return None

    def residual(self, u: FloatArray) -> FloatArray:
        r = self.simulate(u)
        return np.full(self.n_fit, _PENALTY) if r is None else r

    def jacobian(
        self, u: FloatArray, step: float, central: bool, base: FloatArray | None = None
    ) -> FloatArray:
        """Finite-difference Jacobian in the unit box (central where the box allows);
        ``base`` is the residual at ``u`` when already known."""
        r0 = base if base is not None or central else self.simulate(u)
        jac = np.zeros((self.n_fit, u.size))
        for j in range(u.size):
            up, um = u.copy(), u.copy()
            if central and step <= u[j] <= 1 - step:
                up[j] += step
                um[j] -= step
                rp, rm = self.simulate(up), self.simulate(um)
                if rp is not None and rm is not None:
                    jac[:, j] = (rp - rm) / (2 * step)
                continue
            base = r0 if r0 is not None else self.simulate(u)
            h = step if u[j] + step <= 1.0 else -step
            up[j] += h
            rp = self.simulate(up)
            if rp is None:
                up[j] = u[j] - h
                rp, h = self.simulate(up), -h
            if rp is not None and base is not None:
                jac[:, j] = (rp - base) / h
        return jac


def _bounded_params(
    fam: ModelFamily, data: FrictionData, n_fit: int, lo: FloatArray, hi: FloatArray
) -> tuple[Param, ...]:
    """The family's parameters with their resolved bounds and a data-driven start: a linear
    Coulomb + viscous fit of the moving samples; mid-range values for the rest."""
    v = data.velocity_m_per_s[:n_fit]
    f_fit = data.force_n[:n_fit]
    moving = np.abs(v) > 0.1 * np.max(np.abs(v))
    fc, fv = 0.5 * float(np.max(np.abs(f_fit))), 0.0
    if np.count_nonzero(moving) >= 2:
        a = np.column_stack([np.sign(v[moving]), v[moving]])
        sol = np.linalg.lstsq(a, f_fit[moving], rcond=None)[0]
        fc, fv = float(sol[0]), max(float(sol[1]), 0.0)
    n_slip = sum(1 for p in fam.parameters if p.name.startswith("slip_force_n["))
    n_k = sum(1 for p in fam.parameters if p.name.startswith("stiffness_n_per_m["))
    guess = np.empty(lo.size)
    for i, p in enumerate(fam.parameters):
        mid = math.sqrt(lo[i] * hi[i]) if p.log else 0.5 * (lo[i] + hi[i])
        if p.name == _FC.name:
            g = fc
        elif p.name.startswith("slip_force_n["):
            g = fc / n_slip
        elif p.name == _FV.name:
            g = fv
        elif p.name == _DFS.name:
            g = 0.25 * abs(fc)
        elif p.name == _VS.name:
            g = 0.1 * float(np.max(np.abs(v)))
        elif p.name == _DELTA.name:
            g = 2.0
        elif p.name == _DAHL_N.name:
            g = 1.0
        elif p.name == _ASYM.name:
            g = 0.0
        elif p.name.startswith("stiffness_n_per_m["):
            frac = (int(p.name[18:-1]) + 1) / (n_k + 1)
            g = math.exp((1 - frac) * math.log(lo[i]) + frac * math.log(hi[i]))
        else:
            g = mid
        guess[i] = g
    return tuple(
        Param(
            name=p.name,
            unit=p.unit,
            lower=float(lo[i]),
            upper=float(hi[i]),
            initial=float(guess[i]),
            log=p.log,
            description=p.description,
        )
        for i, p in enumerate(fam.parameters)
    )


def _run_start(
    prob: _Problem, index: int, u0: FloatArray, max_nfev: int
) -> tuple[StartResult, FloatArray]:
    # The Jacobian is requested at the point whose residual was just computed: keep it
    # (per start, so that concurrent starts share nothing mutable).
    last: list[tuple[FloatArray, FloatArray | None]] = []

    def sim(u: FloatArray) -> FloatArray | None:
        if last and np.array_equal(last[0][0], u):
            return last[0][1]
        r = prob.simulate(u)
        last[:] = [(u.copy(), r)]
        return r

    def fun(u: FloatArray) -> FloatArray:
        r = sim(u)
        return np.full(prob.n_fit, _PENALTY) if r is None else r

    def jac(u: FloatArray) -> FloatArray:
        return prob.jacobian(u, _STEP_OPT, central=False, base=sim(u))

    sol = least_squares(
        fun,
        u0,
        jac=jac,
        bounds=(np.zeros(u0.size), np.ones(u0.size)),
        method="trf",
        x_scale=1.0,
        max_nfev=max_nfev,
    )
    res = StartResult(
        index=index,
        cost=float(sol.cost),
        status=int(sol.status),
        success=bool(sol.status > 0),
        nfev=int(sol.nfev),
        message=str(sol.message),
    )
    return res, np.asarray(sol.x, dtype=np.float64)


def _rms_se(err: FloatArray, n_batches: int = 20) -> float:
    """Standard error of ``sqrt(mean(err²))`` from batch means of ``err²``."""
    if err.size < 2 * n_batches:
        n_batches = max(2, err.size // 2)
    e2 = err**2
    means = np.array([np.mean(b) for b in np.array_split(e2, n_batches)])
    rms = float(np.sqrt(np.mean(e2)))
    if rms == 0:
        return 0.0
    return float(np.std(means, ddof=1) / math.sqrt(n_batches) / (2 * rms))


def _covariance(
    prob: _Problem, u: FloatArray, r: FloatArray
) -> tuple[FloatArray, FloatArray, list[ParameterStatus]]:
    """Covariance (physical units), standard errors and status per parameter."""
    p = u.size
    at_bound = (u <= _AT_BOUND) | (u >= 1 - _AT_BOUND)
    status: list[ParameterStatus] = ["at_bound" if b else "ok" for b in at_bound]
    free = np.flatnonzero(~at_bound)
    cov_int = np.full((p, p), np.nan)
    se_int = np.full(p, np.nan)
    if free.size:
        # In the unit box every column is the effect of moving across the whole bound range.
        jac = prob.jacobian(u, _STEP_COV, central=True)[:, free]
        dof = max(r.size - free.size, 1)
        s2 = float(np.sum(r**2)) / dof
        _, sv, vt = np.linalg.svd(jac, full_matrices=False)
        keep = sv > _RCOND * sv[0] if sv[0] > 0 else np.zeros(sv.size, dtype=bool)
        v_k = vt[keep]
        cov_u = (v_k.T / sv[keep] ** 2) @ v_k * s2
        se_u = np.sqrt(np.abs(np.diag(cov_u)))
        null_share = np.sum(vt[~keep] ** 2, axis=0)
        bad = (null_share > _NULL_SHARE) | ~(se_u <= _MAX_SE_U)
        w = prob.width[free]
        cov_f = cov_u * np.outer(w, w)
        cov_f[bad, :] = np.nan
        cov_f[:, bad] = np.nan
        cov_int[np.ix_(free, free)] = cov_f
        se_f = se_u * w
        se_f[bad] = np.inf
        se_int[free] = se_f
        for k, j in enumerate(free):
            if bad[k]:
                status[j] = "non_identifiable"
    theta = prob.theta(u)
    dscale = np.where(prob.log, theta, 1.0)
    cov = cov_int * np.outer(dscale, dscale)
    se = se_int * dscale
    return cov, se, status


@single_threaded_blas()
def fit_friction(
    data: FrictionData,
    model: str | ModelFamily = "lugre",
    *,
    bounds: Bounds | None = None,
    n_starts: int = 8,
    seed: int = 0,
    holdout: float = 0.25,
    max_nfev: int | None = None,
    workers: int | None = None,
    integrator: IntegratorOptions | None = None,
    progress: Progress | None = None,
) -> FrictionFit:
    """Fit a friction model to a record by bounded multi-start least squares.

    Parameters
    ----------
    data : the record.
    model : a name in :data:`MODELS` or a :class:`ModelFamily`.
    bounds : ``{name: (lower, upper)}`` replacing some default bounds (physical units).
    n_starts : number of starts (≥ 1): the data-driven guess plus ``n_starts − 1``
        Latin-hypercube points.
    seed : seeds the Latin hypercube; the result does not depend on ``workers``.
    holdout : fraction of the record held out at its end (contiguous), in [0, 0.9].
    max_nfev : residual evaluations per start (default ``40 + 20·p``).
    workers : threads running starts concurrently (default: CPU count); the Rust core
        releases the GIL.
    integrator : integrator options of the model evaluation (default ``rtol = 1e-8``).
    progress : called as ``progress(done, n_starts)`` after each start.

    Returns
    -------
    FrictionFit

    Raises ``nanostage.ConfigError`` for an unknown model, bad bounds, a bad ``holdout`` or
    ``n_starts``, or too few samples for the number of parameters.
    """
    t_start = time.perf_counter()
    fam = _resolve_family(model)
    if not (isinstance(n_starts, int) and n_starts >= 1):
        raise ConfigError(f"n_starts = {n_starts!r} is invalid: expected an integer ≥ 1")
    if max_nfev is not None and not (isinstance(max_nfev, int) and max_nfev >= 1):
        raise ConfigError(f"max_nfev = {max_nfev!r} is invalid: expected an integer ≥ 1")
    if workers is not None and not (isinstance(workers, int) and workers >= 1):
        raise ConfigError(f"workers = {workers!r} is invalid: expected an integer ≥ 1")
    n_fit = _split_index(data.n_samples, holdout, allow_zero=True)
    p = fam.n_params
    if n_fit <= p + 1:
        raise ConfigError(
            f"data has {n_fit} samples to fit, which is too few for {fam.name!r} "
            f"({p} parameters): expected more than {p + 1}"
        )
    fit_part = data._slice(0, n_fit)
    scales = DataScales.from_data(fit_part)
    params = _bounded_params(fam, data, n_fit, *_resolve_bounds(fam, scales, bounds))
    prob = _Problem(fam, data, n_fit, params, integrator)
    # Every model in the box is valid iff both corners are (the ranges are boxes).
    for corner in (np.zeros(p), np.ones(p)):
        try:
            friction_response(
                fam.build(prob.theta(corner)),
                data.time_s[:2],
                data.position_m[:2],
                data.velocity_m_per_s[:2],
                position_friction=fam.position(prob.theta(corner)),
            )
        except ConfigError as e:
            raise ConfigError(f"bounds of {fam.name!r} give an invalid model: {e}") from e
        except SimulationError:
            pass

    starts = [np.clip(prob.u_of(np.array([q.initial for q in params])), 0.01, 0.99)]
    if n_starts > 1:
        lhs = qmc.LatinHypercube(d=p, rng=np.random.default_rng(seed)).random(n_starts - 1)
        starts += [np.clip(row, 1e-3, 1 - 1e-3) for row in lhs]
    nfev = max_nfev if max_nfev is not None else 40 + 20 * p
    n_workers = min(workers or os.cpu_count() or 1, n_starts)
    outcomes: list[tuple[StartResult, FloatArray] | None] = [None] * n_starts
    if n_workers == 1:
        for i, u0 in enumerate(starts):
            outcomes[i] = _run_start(prob, i, u0, nfev)
            if progress is not None:
                progress(i + 1, n_starts)
    else:
        with ThreadPoolExecutor(max_workers=n_workers) as pool:
            futures = {pool.submit(_run_start, prob, i, u0, nfev): i for i, u0 in enumerate(starts)}
            try:
                for done, fut in enumerate(as_completed(futures), start=1):
                    outcomes[futures[fut]] = fut.result()
                    if progress is not None:
                        progress(done, n_starts)
            except BaseException:
                # A failing callback or an interrupt: drop the starts not yet running.
                pool.shutdown(wait=False, cancel_futures=True)
                raise
    results = [o for o in outcomes if o is not None]
    best_i = min(range(len(results)), key=lambda i: (results[i][0].cost, i))
    best, u_best = results[best_i]

    r = prob.residual(u_best)
    cov, se, status = _covariance(prob, u_best, r)
    theta = prob.theta(u_best)
    component = fam.build(theta)
    position = fam.position(theta)
    f_all = _response(component, data, None, integrator, position)
    err = f_all - data.force_n
    rss = float(np.sum(err[:n_fit] ** 2))
    n_hold = data.n_samples - n_fit
    rms_hold = float(np.sqrt(np.mean(err[n_fit:] ** 2))) if n_hold else math.nan
    aic, bic = information_criteria(rss, n_fit, p)
    names = fam.parameter_names
    tol = 1e-3 * best.cost + 1e-12
    return FrictionFit(
        model=fam.name,
        parameters={n: float(x) for n, x in zip(names, theta, strict=True)},
        std_errors={n: float(x) for n, x in zip(names, se, strict=True)},
        parameter_status=dict(zip(names, status, strict=True)),
        bounds={q.name: (q.lower, q.upper) for q in params},
        covariance=cov,
        n_params=p,
        n_fit=n_fit,
        n_holdout=n_hold,
        rms_fit_n=math.sqrt(rss / n_fit),
        rms_holdout_n=rms_hold,
        rms_holdout_se_n=_rms_se(err[n_fit:]) if n_hold else math.nan,
        aic=aic,
        bic=bic,
        component=component,
        predicted_force_n=f_all,
        success=best.success,
        n_starts=n_starts,
        n_converged=sum(1 for s, _ in results if s.success),
        n_at_best=sum(1 for s, _ in results if s.cost <= best.cost + tol),
        starts=tuple(s for s, _ in results),
        elapsed_s=time.perf_counter() - t_start,
        position_friction=position,
    )


# ----- model comparison -----------------------------------------------------------------------


@dataclass(frozen=True, slots=True, kw_only=True)
class ModelComparison:
    """Fits of several models on the same split, ranked by held-out RMS (by BIC when nothing
    is held out), and the selected model ``best`` (see the module docstring for ``rule``)."""

    fits: tuple[FrictionFit, ...]
    best: FrictionFit
    rule: Literal["one_se", "bic"]
    #: Held-out RMS threshold of the one-standard-error rule, N (NaN for ``bic``).
    threshold_n: float

    @property
    def names(self) -> tuple[str, ...]:
        """Model names in rank order."""
        return tuple(f.model for f in self.fits)

    def __getitem__(self, name: str) -> FrictionFit:
        for f in self.fits:
            if f.model == name:
                return f
        raise KeyError(f"{name!r} is not among the compared models {list(self.names)}")

    def to_markdown(self) -> str:
        """The ranking as a Markdown table; the selected model is marked with ✓."""
        lines = [
            "| rank | model | params | fit RMS (N) | held-out RMS (N) | ± SE (N) | AIC | BIC "
            "| starts converged | selected |",
            "|---:|---|---:|---:|---:|---:|---:|---:|---:|:---:|",
        ]
        for k, f in enumerate(self.fits, start=1):
            mark = "✓" if f is self.best else ""
            lines.append(
                f"| {k} | {f.model} | {f.n_params} | {f.rms_fit_n:.4g} | "
                f"{f.rms_holdout_n:.4g} | {f.rms_holdout_se_n:.2g} | {f.aic:.1f} | "
                f"{f.bic:.1f} | {f.n_converged}/{f.n_starts} | {mark} |"
            )
        note = (
            f"Selected by the one-standard-error rule: fewest parameters with held-out RMS "
            f"≤ {self.threshold_n:.4g} N."
            if self.rule == "one_se"
            else "Selected by the smallest BIC on the fit part."
        )
        return "\n".join([*lines, "", note])


def compare_models(
    data: FrictionData,
    models: Sequence[str | ModelFamily] = DEFAULT_COMPARISON,
    *,
    rule: Literal["one_se", "bic"] = "one_se",
    bounds: Mapping[str, Bounds] | None = None,
    n_starts: int = 8,
    seed: int = 0,
    holdout: float = 0.25,
    max_nfev: int | None = None,
    workers: int | None = None,
    integrator: IntegratorOptions | None = None,
    progress: Progress | None = None,
) -> ModelComparison:
    """Fit each model (same split and seed) and select one.

    ``bounds`` maps a model name to its bound overrides. ``rule="one_se"`` needs a held-out
    part and falls back to ``"bic"`` when ``holdout == 0``. ``progress(done, total)`` counts
    starts over all models. Other arguments as in :func:`fit_friction`.
    """
    fams = [_resolve_family(m) for m in models]
    if not fams:
        raise ConfigError("models is empty: expected at least one model")
    names = [f.name for f in fams]
    if len(set(names)) != len(names):
        raise ConfigError(f"models = {names} is invalid: expected distinct models")
    if rule not in ("one_se", "bic"):
        raise ConfigError(f"rule = {rule!r} is invalid: expected 'one_se' or 'bic'")
    for key in bounds or {}:
        if key not in names:
            raise ConfigError(f"bounds[{key!r}] is invalid: expected a compared model {names}")
    total = len(fams) * n_starts if isinstance(n_starts, int) else 0
    fits: list[FrictionFit] = []
    for k, fam in enumerate(fams):
        offset = k * n_starts

        def sub(done: int, _n: int, offset: int = offset) -> None:
            if progress is not None:
                progress(offset + done, total)

        fits.append(
            fit_friction(
                data,
                fam,
                bounds=(bounds or {}).get(fam.name),
                n_starts=n_starts,
                seed=seed,
                holdout=holdout,
                max_nfev=max_nfev,
                workers=workers,
                integrator=integrator,
                progress=sub,
            )
        )
    if holdout == 0:
        rule = "bic"
    if rule == "bic":
        ranked = sorted(fits, key=lambda f: f.bic)
        return ModelComparison(fits=tuple(ranked), best=ranked[0], rule=rule, threshold_n=math.nan)
    ranked = sorted(fits, key=lambda f: f.rms_holdout_n)
    threshold = ranked[0].rms_holdout_n + ranked[0].rms_holdout_se_n
    best = simplest_of_ties(
        ranked, lambda f: f.rms_holdout_n <= threshold, lambda f: (f.n_params, f.rms_holdout_n)
    )
    return ModelComparison(fits=tuple(ranked), best=best, rule=rule, threshold_n=threshold)
