"""Argument checks shared by the library's entry points (one message format everywhere)."""

from __future__ import annotations

import numbers
from typing import Literal

from ._core import ConfigError

__all__ = ["executor_arg", "int_arg"]


def int_arg(
    name: str,
    value: object,
    lo: int,
    hi: int,
    *,
    wording: Literal["invalid", "outside"] = "invalid",
    strict: bool = False,
) -> int:
    """``value`` as an int in ``[lo, hi]`` (a bool is not an integer).

    ``wording`` is the message family of the caller:

    - ``"invalid"`` (entry points and settings): ``TypeError`` ``"{name} must be an int,
      not {type}"``; ``ConfigError`` ``"{name} = {value} is invalid: expected an integer in
      [lo, hi]"``.
    - ``"outside"`` (the test cycles, worded like their real-valued checks): ``TypeError``
      ``"{name} must be an integer, got {value!r}"``; ``ConfigError`` ``"{name} = {value!r}
      is outside [lo, hi]"``.

    ``strict`` (a settings field recorded as JSON): only a Python ``int`` is an integer
    (not a numpy integer), and a value that is not one raises the same ``ConfigError`` as a
    value outside the range.

    Raises
    ------
    TypeError
        ``value`` is not an integer (not with ``strict``).
    ConfigError
        ``value`` is outside ``[lo, hi]`` (with ``strict``, also: not an integer).
    """
    is_int = isinstance(value, int) if strict else isinstance(value, numbers.Integral)
    if isinstance(value, bool) or not is_int:
        if strict:
            raise ConfigError(f"{name} = {value!r} is invalid: expected an integer in [{lo}, {hi}]")
        if wording == "outside":
            raise TypeError(f"{name} must be an integer, got {value!r}")
        raise TypeError(f"{name} must be an int, not {type(value).__name__}")
    assert isinstance(value, numbers.Integral)
    v = int(value)
    if not lo <= v <= hi:
        shown = repr(value) if strict or wording == "outside" else str(v)
        if wording == "outside":
            raise ConfigError(f"{name} = {shown} is outside [{lo}, {hi}]")
        raise ConfigError(f"{name} = {shown} is invalid: expected an integer in [{lo}, {hi}]")
    return v


def executor_arg(executor: object) -> None:
    """Check an ``executor=`` argument before any work: None, or anything with a callable
    ``submit`` (a :class:`concurrent.futures.Executor`, a ``dask.distributed.Client``);
    else ``TypeError`` naming its type."""
    if executor is not None and not callable(getattr(executor, "submit", None)):
        raise TypeError(
            f"executor must have a submit method (concurrent.futures.Executor or a "
            f"dask.distributed.Client), not {type(executor).__name__}"
        )
