"""Argument checks shared by the library's entry points (one message format everywhere)."""

from __future__ import annotations

import numpy as np

from ._core import ConfigError

__all__ = ["int_arg"]


def int_arg(name: str, value: object, lo: int, hi: int) -> int:
    """``value`` as an int in ``[lo, hi]``.

    Raises
    ------
    TypeError
        ``value`` is not an integer (a bool is not).
    ConfigError
        ``value`` is outside ``[lo, hi]``.
    """
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name} must be an int, not {type(value).__name__}")
    v = int(value)
    if not lo <= v <= hi:
        raise ConfigError(f"{name} = {v} is invalid: expected an integer in [{lo}, {hi}]")
    return v
