"""One measured (or simulated) closed-loop experiment in the standard trace format.

Every channel is a 1-D ``float64`` array with one entry per sample, SI units, and the same
length as ``time_s``. Optional channels are ``None`` when the experiment did not record
them. This is the format the gap diagnosis reads and the EMPS loader produces.

Columns (the names a trace file uses):

``time_s``
    Sample instants, s, strictly increasing.
``reference_m``
    The position set-point, m.
``position_m``
    The feedback sensor reading (the encoder), m.
``command_v``
    Controller output (drive command), V. Optional.
``interferometer_m``
    An independent measurement of the true table position, m. Optional.
``disturbance_v``
    Known additive command disturbance, V, added after the controller's saturation.
    Optional.
``disturbance_n``
    Known force disturbance on the table, N, positive along +x. Optional.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

__all__ = ["OPTIONAL_COLUMNS", "REQUIRED_COLUMNS", "Experiment"]

FloatArray = npt.NDArray[np.float64]

#: Columns every trace must have.
REQUIRED_COLUMNS: tuple[str, ...] = ("time_s", "reference_m", "position_m")
#: Columns a trace may have.
OPTIONAL_COLUMNS: tuple[str, ...] = (
    "command_v",
    "interferometer_m",
    "disturbance_v",
    "disturbance_n",
)


@dataclass(frozen=True, slots=True, kw_only=True)
class Experiment:
    """One experiment: the channels above plus a name and where it came from."""

    name: str
    time_s: FloatArray
    reference_m: FloatArray
    position_m: FloatArray
    command_v: FloatArray | None = None
    interferometer_m: FloatArray | None = None
    disturbance_v: FloatArray | None = None
    disturbance_n: FloatArray | None = None
    #: File (and window) the experiment was read from, for error messages and reports.
    source: str = ""
    #: Median sample period, computed once (the diagnosis checks it on every simulation).
    _sample_period_s: float = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        n = len(self.time_s)
        for col in REQUIRED_COLUMNS + OPTIONAL_COLUMNS:
            arr = getattr(self, col)
            if arr is None:
                continue
            if np.ndim(arr) != 1 or len(arr) != n:
                raise ValueError(
                    f"{self.source or self.name}: column {col!r} has shape {np.shape(arr)}, "
                    f"expected ({n},) like time_s"
                )
        period = float(np.median(np.diff(self.time_s))) if n > 1 else 0.0
        object.__setattr__(self, "_sample_period_s", period)

    @property
    def n_samples(self) -> int:
        """Number of samples."""
        return len(self.time_s)

    @property
    def sample_period_s(self) -> float:
        """Median sample period, s."""
        return self._sample_period_s

    def window(self, start_s: float, stop_s: float, name: str | None = None) -> Experiment:
        """The samples with ``start_s <= time_s < stop_s``, time kept as is."""
        keep = (self.time_s >= start_s) & (self.time_s < stop_s)

        def cut(a: FloatArray | None) -> FloatArray | None:
            return None if a is None else a[keep]

        return Experiment(
            name=name or f"{self.name}[{start_s:g}:{stop_s:g} s]",
            source=f"{self.source} window [{start_s:g}, {stop_s:g}) s",
            time_s=self.time_s[keep],
            reference_m=self.reference_m[keep],
            position_m=self.position_m[keep],
            command_v=cut(self.command_v),
            interferometer_m=cut(self.interferometer_m),
            disturbance_v=cut(self.disturbance_v),
            disturbance_n=cut(self.disturbance_n),
        )
