"""Friction components on their own: the force a friction model produces along a prescribed
(measured) motion. The integration runs in the Rust core (``rust/src/model/response.rs``).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from . import _core
from .config import DahlFriction, IntegratorOptions
from .effects import Gms, LuGre, PositionFriction, StaticFrictionMap
from .simulate import interrupt_stop

__all__ = ["FrictionModel", "friction_response"]

FrictionModel = StaticFrictionMap | DahlFriction | LuGre | Gms
FloatArray = npt.NDArray[np.float64]


def friction_response(
    friction: FrictionModel,
    time_s: npt.ArrayLike,
    position_m: npt.ArrayLike,
    velocity_m_per_s: npt.ArrayLike,
    *,
    position_friction: PositionFriction | None = None,
    integrator: IntegratorOptions | None = None,
) -> FloatArray:
    """Force (N) of ``friction`` along the motion, one value per sample, from relaxed
    internal states. Between samples position and velocity are interpolated linearly.

    Static maps give their sliding force (0 where the velocity is exactly 0, where a static
    map's force is set by the rest of the system); ``memory_lag_s`` makes the Stribeck term
    follow the lagged velocity. ``position_friction`` modulates the levels along ``x``.

    Raises ``nanostage.ConfigError`` naming the field for bad parameters, lengths, NaNs or
    a time that does not increase.
    """
    t = np.ascontiguousarray(time_s, dtype=np.float64)
    x = np.ascontiguousarray(position_m, dtype=np.float64)
    v = np.ascontiguousarray(velocity_m_per_s, dtype=np.float64)
    for name, a in (("time_s", t), ("position_m", x), ("velocity_m_per_s", v)):
        if a.ndim != 1:
            raise _core.ConfigError(
                f"{name} = array of shape {a.shape} is invalid: expected a 1-D array"
            )
    terms = list(position_friction.terms) if position_friction is not None else []
    return _core.friction_response(
        friction,
        t,
        x,
        v,
        integrator or IntegratorOptions(rtol=1e-8),
        terms,
        stop=interrupt_stop(),
    )
