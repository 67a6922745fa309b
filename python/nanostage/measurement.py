"""The measurement chain of an ISO 230-2 test: what the interferometer reads at the functional
point, beside what the loop's encoder reads.

The closed loop (:mod:`nanostage.campaign`) servoes the encoder reading; the table's position
at a measurement instant is the simulated ``position_m``. An ISO 230-2 test reads a laser
interferometer at the *functional point* (the tool, the probe, the part), which differs from
the table position in the encoder's scale coordinates by out-of-loop effects. Each is a
frozen dataclass with SI parameters (units in the names), collected in a
:class:`MeasurementChain`:

* :class:`ScaleError`: a linear error of the encoder scale (its accuracy grade, µm/m);
* :class:`AbbeError`: pitch or yaw of the carriage (a smooth function of position, a
  direction-dependent part and a random angular repeatability) times the Abbe offset
  between the scale and the functional point;
* :class:`ThermalDrift`: scale and structure expansion with a first-order temperature rise;
* :class:`SettlingResidual`: motion of the functional point not finished at the reading
  (a decaying oscillation and a creep after each move);
* :class:`InterferometerEnvironment`: the interferometer's noise and the drift of the air's
  refractive index over the measured path plus the dead path.

The encoder's interpolation (sub-divisional) error acts *inside* the loop (the loop servoes
the erroneous reading, so the table ends off by the error, and the interferometer sees it):
it is :class:`nanostage.effects.EncoderErrors` on the simulated system, not a part of this
chain.

Every effect acts per reading, at the measurement instants of the test cycle
(:attr:`nanostage.cycles.Cycle.measure_time_s`, counted from the start of the test), so the
chain is vectorised numpy applied after the campaign:
``interferometer_m = position_m + chain.error_m(...)``. Random parts (angular repeatability,
the phase of a residual oscillation, interferometer noise) are drawn per trial from a
generator seeded by ``(seed, trial)`` only, so a campaign's readings do not depend on its
chunking or thread count.

Equations, valid ranges and typical values with their sources: ``docs/effects.md``,
"Out-of-loop effects: the measurement chain".
"""

from __future__ import annotations

import csv
import math
import numbers
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Final

import numpy as np
import numpy.typing as npt

from . import iso230_2
from ._core import ConfigError
from .csvfile import open_csv, read_header, skip_row

__all__ = [
    "AbbeError",
    "InterferometerEnvironment",
    "IsoMeasurement",
    "MeasurementChain",
    "ScaleError",
    "SettlingResidual",
    "ThermalDrift",
    "arrival_times",
    "read_iso_measurement",
]

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

#: Largest position-like length of the chain [m] (datums, offsets, dead path).
MAX_LENGTH_M: Final[float] = 10.0
#: Largest time-like parameter [s].
MAX_TIME_S: Final[float] = 1e7
#: Tags of the per-trial random streams (one generator per trial and component kind).
_STREAM_ABBE: Final[int] = 0xABBE
_STREAM_SETTLING: Final[int] = 0x5E77
_STREAM_INTERFEROMETER: Final[int] = 0x1F0


def _check(
    owner: object,
    name: str,
    lo: float,
    hi: float,
    unit: str,
    *,
    lo_open: bool = False,
    hi_open: bool = False,
) -> None:
    """Check the field ``name`` of ``owner`` is a finite real in the range (one-line error)."""
    value = getattr(owner, name)
    label = f"{type(owner).__name__}.{name}"
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ConfigError(f"{label} = {value!r} is invalid: expected a real number [{unit}]")
    v = float(value)
    ok = math.isfinite(v) and (v > lo if lo_open else v >= lo) and (v < hi if hi_open else v <= hi)
    if not ok:
        rng = f"{'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
        raise ConfigError(f"{label} = {value!r} is invalid: expected a value in {rng} {unit}")


@dataclass(frozen=True, slots=True, kw_only=True)
class ScaleError:
    """Linear error of the encoder scale: the loop puts the table at
    ``x + linear_error_m_per_m · (x − datum_m)`` when the scale reads ``x``.

    Attributes
    ----------
    linear_error_m_per_m : float
        Scale error per length [m/m], in [-1e-3, 1e-3] (an accuracy grade of ±5 µm/m is
        up to 5e-6).
    datum_m : float
        Where the scale's error is zero (its fixing point, or the test's zero) [m], in
        [-10, 10].
    """

    linear_error_m_per_m: float = 0.0
    datum_m: float = 0.0

    def __post_init__(self) -> None:
        _check(self, "linear_error_m_per_m", -1e-3, 1e-3, "m/m")
        _check(self, "datum_m", -MAX_LENGTH_M, MAX_LENGTH_M, "m")

    def error_m(self, position_m: FloatArray) -> FloatArray:
        """Error of the functional point [m] at ``position_m``."""
        out: FloatArray = self.linear_error_m_per_m * (position_m - self.datum_m)
        return out


@dataclass(frozen=True, slots=True, kw_only=True)
class AbbeError:
    """Angular error of the carriage (pitch or yaw) times the Abbe offset.

    The angle at position ``x``, approached in direction ``d = ±1``, is ::

        θ(x, d) = angle_rad + slope_rad_per_m·u + curvature_rad_per_m2·u²
                  + wave_amplitude_rad·sin(2π x / wave_period_m + wave_phase_rad)
                  + d · reversal_rad / 2 + noise_std_rad · N(0, 1),      u = x − centre_m

    and the functional point is ahead of the scale reading by ``offset_m · tan θ``. Use one
    component for pitch (offset: the height of the functional point above the scale) and one
    for yaw (the lateral offset).

    Attributes
    ----------
    offset_m : float
        Abbe offset between the scale's measuring line and the functional point [m], in
        [-1, 1]; the sign says on which side.
    angle_rad, slope_rad_per_m, curvature_rad_per_m2 : float
        Smooth part of the angle: constant [rad] in [-0.1, 0.1], slope [rad/m] and
        curvature [rad/m²] in [-1e3, 1e3] about ``centre_m``.
    wave_amplitude_rad, wave_period_m, wave_phase_rad : float
        A periodic part (guide waviness, ball recirculation): amplitude [rad] in [0, 0.1],
        period [m] in (0, 10], phase [rad] in [-2π, 2π].
    reversal_rad : float
        Angle of the ↑ approach minus that of the ↓ approach (the carriage tilts with the
        direction of the drive force) [rad], in [-0.1, 0.1].
    noise_std_rad : float
        Angular repeatability: a normal draw per reading [rad], in [0, 0.01].
    centre_m : float
        Position the smooth part is expanded about [m], in [-10, 10].
    """

    offset_m: float
    angle_rad: float = 0.0
    slope_rad_per_m: float = 0.0
    curvature_rad_per_m2: float = 0.0
    wave_amplitude_rad: float = 0.0
    wave_period_m: float = 0.01
    wave_phase_rad: float = 0.0
    reversal_rad: float = 0.0
    noise_std_rad: float = 0.0
    centre_m: float = 0.0

    def __post_init__(self) -> None:
        _check(self, "offset_m", -1.0, 1.0, "m")
        _check(self, "angle_rad", -0.1, 0.1, "rad")
        _check(self, "slope_rad_per_m", -1e3, 1e3, "rad/m")
        _check(self, "curvature_rad_per_m2", -1e3, 1e3, "rad/m²")
        _check(self, "wave_amplitude_rad", 0.0, 0.1, "rad")
        _check(self, "wave_period_m", 0.0, MAX_LENGTH_M, "m", lo_open=True)
        _check(self, "wave_phase_rad", -2.0 * math.pi, 2.0 * math.pi, "rad")
        _check(self, "reversal_rad", -0.1, 0.1, "rad")
        _check(self, "noise_std_rad", 0.0, 0.01, "rad")
        _check(self, "centre_m", -MAX_LENGTH_M, MAX_LENGTH_M, "m")

    def angle_rad_at(
        self, position_m: FloatArray, direction: npt.ArrayLike, noise: FloatArray | None = None
    ) -> FloatArray:
        """The angle θ [rad] at ``position_m`` (any shape) approached in ``direction``
        (±1, broadcast); ``noise``: standard normal draws of the same shape (or None)."""
        u = position_m - self.centre_m
        theta = (
            self.angle_rad
            + self.slope_rad_per_m * u
            + self.curvature_rad_per_m2 * u * u
            + self.wave_amplitude_rad
            * np.sin(2.0 * math.pi * position_m / self.wave_period_m + self.wave_phase_rad)
            + np.asarray(direction, dtype=np.float64) * (0.5 * self.reversal_rad)
        )
        if noise is not None and self.noise_std_rad > 0.0:
            theta = theta + self.noise_std_rad * noise
        out: FloatArray = np.asarray(theta, dtype=np.float64)
        return out

    def error_m(
        self, position_m: FloatArray, direction: npt.ArrayLike, noise: FloatArray | None = None
    ) -> FloatArray:
        """Error of the functional point, ``offset_m · tan θ`` [m]."""
        out: FloatArray = self.offset_m * np.tan(self.angle_rad_at(position_m, direction, noise))
        return out


@dataclass(frozen=True, slots=True, kw_only=True)
class ThermalDrift:
    """Expansion of the scale and the structure under a first-order temperature rise.

    A heat source (the motor, the lamp, the operator) switched on ``test_start_s`` before
    the test raises the temperature towards ``temperature_rise_k`` with time constant
    ``time_constant_s``; the rise *during the test* (``t`` from the test's start, when both
    instruments are zeroed) is ::

        ΔT(t) = temperature_rise_k · (exp(−t₀/τ) − exp(−(t₀ + t)/τ)),   t₀ = test_start_s

    and the functional point moves by ::

        δ(x, t) = [scale_expansion_per_k · (x − scale_datum_m) + structure_m_per_k] · ΔT(t)

    The first term is the scale's expansion about its fixing point (the loop holds the scale
    reading, so the table goes with the scale); the second lumps every expansion of the
    metrology loop between the scale's fixing point and the interferometer (carriage,
    base, the functional point's bracket) as a length change per kelvin. The ball screw's
    expansion is inside the position loop when the encoder is on the table (the seed axis)
    and moves nothing the interferometer sees.

    Attributes
    ----------
    temperature_rise_k : float
        Final temperature rise [K], in [-50, 50].
    time_constant_s : float
        Time constant of the rise [s], in (0, 1e7].
    test_start_s : float
        Time from switching the heat source on to the start of the test [s], in [0, 1e7].
    scale_expansion_per_k : float
        Expansion coefficient of the scale [1/K], in [-1e-4, 1e-4].
    scale_datum_m : float
        The scale's fixing point (thermal datum) [m], in [-10, 10].
    structure_m_per_k : float
        Shift of the functional point relative to the interferometer per kelvin [m/K], in
        [-1e-3, 1e-3] (α · L of the structural loop: 23e-6 /K · 0.1 m = 2.3e-6 m/K).
    """

    temperature_rise_k: float = 0.0
    time_constant_s: float = 1800.0
    test_start_s: float = 0.0
    scale_expansion_per_k: float = 0.0
    scale_datum_m: float = 0.0
    structure_m_per_k: float = 0.0

    def __post_init__(self) -> None:
        _check(self, "temperature_rise_k", -50.0, 50.0, "K")
        _check(self, "time_constant_s", 0.0, MAX_TIME_S, "s", lo_open=True)
        _check(self, "test_start_s", 0.0, MAX_TIME_S, "s")
        _check(self, "scale_expansion_per_k", -1e-4, 1e-4, "1/K")
        _check(self, "scale_datum_m", -MAX_LENGTH_M, MAX_LENGTH_M, "m")
        _check(self, "structure_m_per_k", -1e-3, 1e-3, "m/K")

    def temperature_k(self, time_s: FloatArray) -> FloatArray:
        """The rise ΔT(t) [K] since the test's start at ``time_s`` [s] from that start."""
        tau = self.time_constant_s
        t0 = self.test_start_s
        out: FloatArray = self.temperature_rise_k * (
            math.exp(-t0 / tau) - np.exp(-(t0 + np.asarray(time_s, dtype=np.float64)) / tau)
        )
        return out

    def error_m(self, position_m: FloatArray, time_s: FloatArray) -> FloatArray:
        """Error of the functional point δ(x, t) [m]."""
        length = self.scale_expansion_per_k * (position_m - self.scale_datum_m)
        out: FloatArray = (length + self.structure_m_per_k) * self.temperature_k(time_s)
        return out


@dataclass(frozen=True, slots=True, kw_only=True)
class SettlingResidual:
    """Motion of the functional point not finished at the reading, after each move.

    With ``t_d`` the time from the move's arrival (the first sample at which the reference
    equals the target) to the reading and ``s`` the move's signed length ::

        δ = (amplitude_m + amplitude_per_move · |s|) · exp(−ζω t_d) · cos(ω_d t_d + φ)
            − creep_fraction · s · exp(−t_d / creep_time_constant_s)

    with ``ω = 2π frequency_hz``, ``ω_d = ω √(1 − ζ²)``, ``ζ = damping_ratio`` and the phase
    ``φ`` drawn per reading uniformly in ``[−phase_spread_rad, phase_spread_rad]`` (the
    instant the loop hands the move over to the structure varies from move to move). The
    oscillation is a structural mode between the encoder and the functional point (the loop
    does not see it); the creep is a slow remainder of the approach (e.g. the functional
    point's bracket relaxing).

    Attributes
    ----------
    amplitude_m : float
        Oscillation amplitude at arrival, whatever the move [m], in [0, 1e-3].
    amplitude_per_move : float
        Oscillation amplitude per length of the move [m/m], in [0, 1].
    frequency_hz : float
        Undamped frequency of the mode [Hz], in (0, 1e5].
    damping_ratio : float
        Damping ratio ζ of the mode, in (0, 1).
    phase_spread_rad : float
        Half-width of the phase's uniform draw [rad], in [0, π] (0: the same phase at
        every reading).
    creep_fraction : float
        Part of the move still to come at arrival, in [0, 0.1].
    creep_time_constant_s : float
        Time constant of the creep [s], in (0, 1e4].
    """

    amplitude_m: float = 0.0
    amplitude_per_move: float = 0.0
    frequency_hz: float = 100.0
    damping_ratio: float = 0.01
    phase_spread_rad: float = math.pi
    creep_fraction: float = 0.0
    creep_time_constant_s: float = 1.0

    def __post_init__(self) -> None:
        _check(self, "amplitude_m", 0.0, 1e-3, "m")
        _check(self, "amplitude_per_move", 0.0, 1.0, "m/m")
        _check(self, "frequency_hz", 0.0, 1e5, "Hz", lo_open=True)
        _check(self, "damping_ratio", 0.0, 1.0, "", lo_open=True, hi_open=True)
        _check(self, "phase_spread_rad", 0.0, math.pi, "rad")
        _check(self, "creep_fraction", 0.0, 0.1, "")
        _check(self, "creep_time_constant_s", 0.0, 1e4, "s", lo_open=True)

    def error_m(
        self, move_m: FloatArray, dwell_s: FloatArray, uniform: FloatArray | None = None
    ) -> FloatArray:
        """Error at the readings [m]: ``move_m`` the signed move lengths, ``dwell_s`` the times
        from arrival; ``uniform``: draws in [−1, 1] scaling the phase spread (or None: φ = 0)."""
        zeta = self.damping_ratio
        omega = 2.0 * math.pi * self.frequency_hz
        omega_d = omega * math.sqrt(1.0 - zeta * zeta)
        amp = self.amplitude_m + self.amplitude_per_move * np.abs(move_m)
        phase = 0.0 if uniform is None else self.phase_spread_rad * uniform
        osc = amp * np.exp(-zeta * omega * dwell_s) * np.cos(omega_d * dwell_s + phase)
        creep = self.creep_fraction * move_m * np.exp(-dwell_s / self.creep_time_constant_s)
        out: FloatArray = np.asarray(osc - creep, dtype=np.float64)
        return out


@dataclass(frozen=True, slots=True, kw_only=True)
class InterferometerEnvironment:
    """The interferometer's own errors: noise, and the air's refractive index drifting
    over the measured path and the dead path.

    The interferometer is zeroed at ``zero_position_m`` at the test's start with its
    wavelength compensated for the air at that instant; the index then changes by
    ``Δn(t) = refractive_index_rate_per_s · t``, and the reading's error is ::

        δ = (dead_path_m + x − zero_position_m) · Δn(t) + noise_std_m · N(0, 1)

    (to first order in Δn; the dead path is the beam between the interferometer optics and
    the zero point). Edlén's sensitivities near 20 °C, 1013 hPa: about −0.93e-6 per K of
    air temperature and +0.27e-6 per hPa (docs/effects.md).

    Attributes
    ----------
    noise_std_m : float
        Standard deviation of the reading's noise (air turbulence, electronics) [m], in
        [0, 1e-3].
    refractive_index_rate_per_s : float
        Uncompensated rate of change of the refractive index [1/s], in [-1e-6, 1e-6]
        (1 K/h of air temperature is about −2.6e-10 /s).
    dead_path_m : float
        Dead path [m], in [0, 10].
    zero_position_m : float
        Position at which the interferometer is zeroed [m], in [-10, 10].
    """

    noise_std_m: float = 0.0
    refractive_index_rate_per_s: float = 0.0
    dead_path_m: float = 0.0
    zero_position_m: float = 0.0

    def __post_init__(self) -> None:
        _check(self, "noise_std_m", 0.0, 1e-3, "m")
        _check(self, "refractive_index_rate_per_s", -1e-6, 1e-6, "1/s")
        _check(self, "dead_path_m", 0.0, MAX_LENGTH_M, "m")
        _check(self, "zero_position_m", -MAX_LENGTH_M, MAX_LENGTH_M, "m")

    def error_m(
        self, position_m: FloatArray, time_s: FloatArray, noise: FloatArray | None = None
    ) -> FloatArray:
        """Error of the reading [m]; ``noise``: standard normal draws (or None)."""
        path = self.dead_path_m + position_m - self.zero_position_m
        out: FloatArray = path * (self.refractive_index_rate_per_s * time_s)
        if noise is not None and self.noise_std_m > 0.0:
            out = out + self.noise_std_m * noise
        return out


@dataclass(frozen=True, slots=True, kw_only=True)
class MeasurementChain:
    """The out-of-loop effects between the table's position and the interferometer's reading
    at the functional point (all off by default: the reading is the table position).

    Attributes
    ----------
    scale : ScaleError or None
    abbe : tuple of AbbeError
        One per angular error (pitch, yaw).
    thermal : ThermalDrift or None
    settling : SettlingResidual or None
    interferometer : InterferometerEnvironment or None
    """

    scale: ScaleError | None = None
    abbe: tuple[AbbeError, ...] = ()
    thermal: ThermalDrift | None = None
    settling: SettlingResidual | None = None
    interferometer: InterferometerEnvironment | None = None

    def __post_init__(self) -> None:
        kinds: dict[str, type | tuple[type, ...]] = {
            "scale": ScaleError,
            "thermal": ThermalDrift,
            "settling": SettlingResidual,
            "interferometer": InterferometerEnvironment,
        }
        for name, kind in kinds.items():
            value = getattr(self, name)
            if value is not None and not isinstance(value, kind):
                raise ConfigError(
                    f"MeasurementChain.{name} = {value!r} is invalid: expected a "
                    f"{getattr(kind, '__name__', kind)} or None"
                )
        if not isinstance(self.abbe, tuple) or not all(isinstance(a, AbbeError) for a in self.abbe):
            raise ConfigError(
                f"MeasurementChain.abbe = {self.abbe!r} is invalid: expected a tuple of "
                "AbbeError (one per angular error)"
            )

    @property
    def is_empty(self) -> bool:
        """No effect switched on (the reading is the table position)."""
        return all(getattr(self, f.name) in (None, ()) for f in fields(self))

    def error_m(
        self,
        *,
        position_m: npt.ArrayLike,
        time_s: npt.ArrayLike,
        direction: npt.ArrayLike,
        move_m: npt.ArrayLike,
        dwell_s: npt.ArrayLike,
        seed: int = 0,
        trials: npt.ArrayLike | None = None,
    ) -> FloatArray:
        """The interferometer's reading minus the table position [m].

        Parameters
        ----------
        position_m : array_like, shape (n_trials, n_measurements)
            Table position at each reading [m] (NaN rows stay NaN).
        time_s, direction, move_m, dwell_s : array_like, shape (n_measurements,)
            Per reading: time from the test's start [s], approach direction (±1), signed
            length of the move that ended before it [m], time from that move's arrival [s]
            (:func:`arrival_times`).
        seed : int
            Seed of the random parts; trial ``i`` draws from ``(seed, trials[i])`` only.
        trials : array_like of int, shape (n_trials,), optional
            Trial index of each row (default ``0..n_trials-1``).

        Returns
        -------
        ndarray of float64, shape (n_trials, n_measurements)
        """
        pos = np.asarray(position_m, dtype=np.float64)
        if pos.ndim != 2:
            raise ConfigError(
                f"position_m = array of shape {pos.shape} is invalid: expected "
                "(n_trials, n_measurements)"
            )
        n_trials, n_meas = pos.shape
        per_reading = {}
        for name, arr in (
            ("time_s", time_s),
            ("direction", direction),
            ("move_m", move_m),
            ("dwell_s", dwell_s),
        ):
            a = np.asarray(arr, dtype=np.float64)
            if a.shape != (n_meas,):
                raise ConfigError(
                    f"{name} = array of shape {a.shape} is invalid: expected ({n_meas},), "
                    "one value per measurement"
                )
            per_reading[name] = a
        t, d = per_reading["time_s"], per_reading["direction"]
        rows = np.arange(n_trials) if trials is None else np.asarray(trials, dtype=np.int64)
        if rows.shape != (n_trials,):
            raise ConfigError(
                f"trials = array of shape {rows.shape} is invalid: expected ({n_trials},)"
            )
        err = np.zeros_like(pos)
        if self.scale is not None:
            err += self.scale.error_m(pos)
        for k, abbe in enumerate(self.abbe):
            noise = (
                _draws(seed, rows, _STREAM_ABBE + k, n_meas, "normal")
                if abbe.noise_std_rad > 0.0
                else None
            )
            err += abbe.error_m(pos, d[None, :], noise)
        if self.thermal is not None:
            err += self.thermal.error_m(pos, t[None, :])
        if self.settling is not None:
            s = self.settling
            uniform = (
                _draws(seed, rows, _STREAM_SETTLING, n_meas, "uniform")
                if s.phase_spread_rad > 0.0
                else None
            )
            err += s.error_m(
                per_reading["move_m"][None, :], per_reading["dwell_s"][None, :], uniform
            )
        if self.interferometer is not None:
            ifm = self.interferometer
            noise = (
                _draws(seed, rows, _STREAM_INTERFEROMETER, n_meas, "normal")
                if ifm.noise_std_m > 0.0
                else None
            )
            err += ifm.error_m(pos, t[None, :], noise)
        return err


def _draws(seed: int, trials: IntArray, stream: int, n: int, kind: str) -> FloatArray:
    """Per-trial draws, shape (len(trials), n): trial ``i`` from ``(seed, trials[i], stream)``
    only (standard normal, or uniform in [−1, 1])."""
    out = np.empty((trials.shape[0], n), dtype=np.float64)
    for row, trial in enumerate(trials):
        rng = np.random.default_rng([int(seed), int(trial), int(stream)])
        out[row] = rng.standard_normal(n) if kind == "normal" else rng.uniform(-1.0, 1.0, n)
    return out


def arrival_times(
    reference_m: npt.ArrayLike, measure_index: npt.ArrayLike, sample_period_s: float
) -> tuple[FloatArray, FloatArray]:
    """For each reading of a cycle, the signed length of the move that ended before it and
    the time from that move's arrival to the reading.

    The arrival is the last sample ``≤ measure_index`` at which the reference changed (the
    first sample at the target); the move started at the last sample before it at which the
    reference held still (the previous stop). A reading with no move before it has move 0
    and is timed from the cycle's start.

    Returns
    -------
    (move_m, dwell_s) : ndarrays of float64, shape (n_measurements,)
    """
    ref = np.asarray(reference_m, dtype=np.float64)
    idx = np.asarray(measure_index, dtype=np.int64)
    changed = np.flatnonzero(ref[1:] != ref[:-1]) + 1  # first sample after each change
    held = np.flatnonzero(ref[1:] == ref[:-1]) + 1  # samples equal to the one before
    k = np.searchsorted(changed, idx, side="right") - 1
    arrival = np.where(k >= 0, changed[np.maximum(k, 0)], 0)
    h = np.searchsorted(held, arrival, side="left") - 1
    start = np.where(h >= 0, held[np.maximum(h, 0)], 0)
    move: FloatArray = np.where(k >= 0, ref[idx] - ref[start], 0.0)
    dwell: FloatArray = (idx - arrival).astype(np.float64) * float(sample_period_s)
    return move, dwell


# --------------------------------------------------------------------------------------------
# A measured ISO 230-2 test with its encoder readings, times and temperatures
# --------------------------------------------------------------------------------------------

#: Plausible temperatures of a test in kelvin (a value outside, e.g. 20, is in °C).
TEMPERATURE_RANGE_K: Final[tuple[float, float]] = (173.15, 373.15)
_CELSIUS_K: Final[float] = 273.15


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class IsoMeasurement:
    """A measured ISO 230-2 test: the interferometer's records and, when the file has them,
    the encoder reading, the time and the temperature of each reading (same order).

    Attributes
    ----------
    records : iso230_2.MeasurementRecords
        Target, direction, run and the interferometer reading (``actual_m``) per reading.
    encoder_m : ndarray of float64 or None
        The encoder (what the loop saw) at each reading [m].
    time_s : ndarray of float64 or None
        Time of each reading from the test's start [s], increasing in file order.
    temperature_k : ndarray of float64 or None
        Temperature at each reading [K].
    """

    records: iso230_2.MeasurementRecords
    encoder_m: FloatArray | None = None
    time_s: FloatArray | None = None
    temperature_k: FloatArray | None = None

    def evaluate(self, *, coverage_factor: float = 2.0) -> iso230_2.Iso230Result:
        """ISO 230-2 evaluation of the interferometer's readings."""
        return self.records.evaluate(coverage_factor=coverage_factor)


def read_iso_measurement(
    path: str | Path,
    *,
    travel_m: tuple[float, float] | None = None,
    units: str | None = None,
    target_tolerance_m: float = 1e-9,
) -> IsoMeasurement:
    """Read a measured ISO 230-2 test and check it whole before any simulation.

    The file is the measurement CSV of :func:`nanostage.iso230_2.read_measurement_csv`
    (``target_m``, ``direction``, ``run``, ``actual_m`` — the interferometer — with its
    checks: units, duplicates, at least 2 runs) with optional columns: ``encoder_m`` (or
    ``encoder_mm``), ``time_s`` (from the test's start) and ``temperature_k`` (or
    ``temperature_c``). Further checks:

    * every target has the runs ``1..n`` in each direction, none missing, and the same ``n``
      at every target and direction (an ISO test approaches every target equally often);
    * with ``travel_m = (lo, hi)``, every target lies in ``[lo, hi]``;
    * the encoder reading differs from the target by a plausible deviation (the unit check
      of ``actual_m``);
    * the times are finite and increase strictly in file order (the order of the test);
    * a ``temperature_k`` lies in [173.15, 373.15] K (20 is a temperature in °C).

    Raises
    ------
    nanostage.iso230_2.Iso230InputError
        ``"<file>, line <n>, column '<name>': <reason>"`` for the first problem found.
    OSError
        If the file cannot be read.
    """
    src = str(path)
    records = iso230_2.read_measurement_csv(
        path, units=units, target_tolerance_m=target_tolerance_m
    )
    line = records.line
    assert line is not None  # a file's records carry their lines
    _check_runs(records, src, target_tolerance_m)
    if travel_m is not None:
        lo, hi = (float(v) for v in travel_m)
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise ConfigError(
                f"travel_m = {travel_m!r} is invalid: expected (lo, hi) with lo < hi [m]"
            )
        bad = np.flatnonzero((records.target_m < lo) | (records.target_m > hi))
        if bad.size:
            i = int(bad[0])
            raise iso230_2.Iso230InputError(
                f"target {float(records.target_m[i]):.9g} m is outside the travel "
                f"[{lo:g}, {hi:g}] m",
                source=src,
                line=int(line[i]),
                column="target_m",
            )
    columns = _optional_columns(Path(path), src, [int(v) for v in line], units)
    encoder = time = temperature = None
    if "encoder" in columns:
        col, encoder = columns["encoder"]
        for i, (t, e) in enumerate(zip(records.target_m, encoder, strict=True)):

            def fail(column: str, message: str, i: int = i) -> iso230_2.Iso230InputError:
                return iso230_2.Iso230InputError(
                    message, source=src, line=int(line[i]), column=column
                )

            iso230_2.evaluation.check_record_units(float(t), float(e), fail, ("target_m", col))
    if "time" in columns:
        col, time = columns["time"]
        steps = np.flatnonzero(np.diff(time) <= 0.0)
        if steps.size:
            i = int(steps[0]) + 1
            raise iso230_2.Iso230InputError(
                f"time {float(time[i]):.9g} s is not after the previous reading's "
                f"{float(time[i - 1]):.9g} s (line {int(line[i - 1])}); the readings must be in "
                "the order of the test, with increasing times",
                source=src,
                line=int(line[i]),
                column=col,
            )
    if "temperature" in columns:
        col, temperature = columns["temperature"]
        if col == "temperature_c":
            temperature = temperature + _CELSIUS_K
        lo_k, hi_k = TEMPERATURE_RANGE_K
        bad = np.flatnonzero((temperature < lo_k) | (temperature > hi_k))
        if bad.size:
            i = int(bad[0])
            raw = float(columns["temperature"][1][i])
            hint = (
                " (a value in °C? name the column temperature_c)" if col == "temperature_k" else ""
            )
            raise iso230_2.Iso230InputError(
                f"temperature {raw:.6g} is outside [{lo_k:g}, {hi_k:g}] K{hint}",
                source=src,
                line=int(line[i]),
                column=col,
            )
    for arr in (encoder, time, temperature):
        if arr is not None:
            arr.flags.writeable = False
    return IsoMeasurement(
        records=records, encoder_m=encoder, time_s=time, temperature_k=temperature
    )


def _check_runs(records: iso230_2.MeasurementRecords, src: str, tolerance_m: float) -> None:
    """Runs 1..n at every target and direction, the same n everywhere."""
    line = records.line
    assert line is not None
    order = np.argsort(records.target_m, kind="stable")
    groups: dict[tuple[int, str], list[int]] = {}
    start = math.nan
    g = -1
    for idx in order:
        t = float(records.target_m[idx])
        if g < 0 or t - start > tolerance_m:
            g += 1
            start = t
        groups.setdefault((g, str(records.direction[idx])), []).append(int(idx))
    expected: int | None = None
    first_key: tuple[int, str] | None = None
    for key in sorted(groups, key=lambda k: min(int(line[i]) for i in groups[k])):
        members = groups[key]
        runs = sorted(int(records.run[i]) for i in members)
        where = min(members, key=lambda i: int(line[i]))
        target = float(records.target_m[where])
        missing = sorted(set(range(1, max(runs) + 1)) - set(runs))
        if missing or runs[0] < 1:
            raise iso230_2.Iso230InputError(
                f"target {target:.9g} m, direction {key[1]!r} has runs {runs}: run(s) "
                f"{missing or [r for r in runs if r < 1]} missing or invalid (expected 1..n)",
                source=src,
                line=int(line[where]),
                column="run",
            )
        if expected is None:
            expected, first_key = len(runs), key
        elif len(runs) != expected:
            assert first_key is not None
            first = min(groups[first_key], key=lambda i: int(line[i]))
            raise iso230_2.Iso230InputError(
                f"target {target:.9g} m, direction {key[1]!r} has {len(runs)} runs but target "
                f"{float(records.target_m[first]):.9g} m, direction {first_key[1]!r} (line "
                f"{int(line[first])}) has {expected}; an ISO 230-2 test approaches every target "
                "equally often",
                source=src,
                line=int(line[where]),
                column="run",
            )


def _optional_columns(
    path: Path, src: str, lines: list[int], units: str | None
) -> dict[str, tuple[str, FloatArray]]:
    """The optional columns' values at the records' lines: kind → (column, values in SI)."""
    kinds = {
        "encoder": [("encoder_m", 1.0), ("encoder_mm", 1e-3)],
        "time": [("time_s", 1.0)],
        "temperature": [("temperature_k", 1.0), ("temperature_c", 1.0)],
    }
    rows: dict[int, list[str]] = {}
    with open_csv(path) as fh:
        reader = csv.reader(fh)
        header, header_line = read_header(reader)
        assert header is not None  # the records were read from this file
        for row in reader:
            if not skip_row(row):
                rows[reader.line_num] = row
    out: dict[str, tuple[str, FloatArray]] = {}
    for kind, options in kinds.items():
        present = [(c, f) for c, f in options if c in header]
        if not present:
            continue
        if len(present) > 1:
            raise iso230_2.Iso230InputError(
                f"both {' and '.join(c for c, _ in present)} in the header; give one",
                source=src,
                line=header_line,
                column=present[0][0],
            )
        col, factor = present[0]
        if kind == "encoder" and units is not None:
            factor = iso230_2.LENGTH_UNITS[units]
        j = header.index(col)
        values = np.empty(len(lines), dtype=np.float64)
        for k, ln in enumerate(lines):
            row = rows[ln]
            text = row[j].strip() if j < len(row) else ""
            try:
                v = float(text)
            except ValueError:
                raise iso230_2.Iso230InputError(
                    "empty value" if not text else f"cannot parse {text!r} as a number",
                    source=src,
                    line=ln,
                    column=col,
                ) from None
            if not math.isfinite(v):
                raise iso230_2.Iso230InputError(
                    f"value {text!r} is not a finite number (NaN/inf)",
                    source=src,
                    line=ln,
                    column=col,
                )
            values[k] = v * factor
        out[kind] = (col, values)
    return out
