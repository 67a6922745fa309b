"""The effect library's components: every effect the gap diagnosis can name, as a frozen
dataclass with physical parameters (SI units in the names). All are off by default; a
:class:`Effects` collects the ones switched on and is part of :class:`nanostage.System`.

Valid ranges are enforced by the Rust core (``rust/src/model/component.rs``) when the system
is built.
The equations are in ``docs/effects.md``; the stable names are in
:data:`EFFECT_NAMES` (the diagnosis refers to effects by these names; they never change
meaning).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

__all__ = [
    "EFFECT_NAMES",
    "AmplifierDynamics",
    "Backlash",
    "DriveCompliance",
    "DwellStaticFriction",
    "Effects",
    "EncoderErrors",
    "FrictionModifiers",
    "Gms",
    "Interferometer",
    "LuGre",
    "PositionFriction",
    "StaticFrictionMap",
    "StochasticFriction",
    "lead_periodic_friction",
    "position_random_friction",
]

Side = Literal["motor", "table"]


@dataclass(frozen=True, slots=True, kw_only=True)
class DwellStaticFriction:
    """Rising static friction with dwell time: ``Fs(θ) = Fs + ΔFs · θ / (θ + γ)``.

    Two laws of the dwell clock ``θ`` (docs/effects.md, *Dwell-time static friction*):

    - breakaway only (``slip_distance_m = None``, the default): ``θ`` is the time the side
      has been stuck, and only the breakaway force rises;
    - contact ageing (``slip_distance_m = D_c``, in [1e-9, 1e-2] m): ``θ`` is the contact age
      of Ruina's ageing law, ``dθ/dt = 1 − |v| · θ / D_c`` (the dwell time at rest, relaxing
      to ``D_c / |v|`` over a slip of about ``D_c``), and ``Fs(θ)`` is also the static level of
      the Stribeck term while sliding, so a slow creep keeps the level raised.
    """

    rise_n: float
    time_constant_s: float
    slip_distance_m: float | None = None


@dataclass(frozen=True, slots=True, kw_only=True)
class StaticFrictionMap:
    """Static friction map with true stiction (Coulomb + viscous, Stribeck), force units:
    ``F = (1 ± a)·[Fc + (Fs − Fc)·exp(−|v_m/vs|^δ)]·sgn v + (1 ± a_v)·Fv·v``. ``Fs = Fc`` gives
    Coulomb + viscous. ``v_m`` is the velocity lagged by ``memory_lag_s`` when set."""

    static_force_n: float
    coulomb_force_n: float
    viscous_n_s_per_m: float = 0.0
    stribeck_velocity_m_per_s: float = 1e-3
    stribeck_exponent: float = 2.0
    asymmetry: float = 0.0
    viscous_asymmetry: float = 0.0
    dwell: DwellStaticFriction | None = None
    memory_lag_s: float | None = None


@dataclass(frozen=True, slots=True, kw_only=True)
class LuGre:
    """LuGre: ``ż = v − σ0·|v|·z/g(v)``, ``F = σ0·z + σ1·ż + σ2·v``. ``coulomb_force_n`` in
    [1e-6, 1e5] N and ``stiffness_n_per_m`` in [1e-3, 1e12] N/m, as for
    :class:`nanostage.DahlFriction`. ``asymmetry`` (a, in [-0.9, 0.9]) scales both levels
    of ``g(v)`` by ``1 + a·sgn v`` (steady sliding ``Fc·(1 ± a)``)."""

    stiffness_n_per_m: float
    damping_n_s_per_m: float
    viscous_n_s_per_m: float
    coulomb_force_n: float
    static_force_n: float
    stribeck_velocity_m_per_s: float
    asymmetry: float = 0.0


@dataclass(frozen=True, slots=True, kw_only=True)
class Gms:
    """Generalized Maxwell-slip: parallel elasto-slide elements with Stribeck slip forces
    (``weights`` sum to 1; element ``i`` slips at ``weights[i]·s(v)``). ``coulomb_force_n``
    in [1e-6, 1e5] N and each stiffness in [1e-3, 1e12] N/m, as for
    :class:`nanostage.DahlFriction`. ``asymmetry`` (a, in [-0.9, 0.9]) scales the slip
    force ``s(v)`` by ``1 + a·sgn v`` (steady sliding ``Fc·(1 ± a)``)."""

    stiffness_n_per_m: tuple[float, ...]
    weights: tuple[float, ...]
    coulomb_force_n: float
    static_force_n: float
    stribeck_velocity_m_per_s: float
    viscous_n_s_per_m: float = 0.0
    asymmetry: float = 0.0


@dataclass(frozen=True, slots=True, kw_only=True)
class FrictionModifiers:
    """Asymmetry, dwell-time static friction and frictional memory of the motor-shaft map."""

    asymmetry: float = 0.0
    dwell: DwellStaticFriction | None = None
    memory_lag_s: float | None = None


@dataclass(frozen=True, slots=True, kw_only=True)
class PositionFriction:
    """Friction levels of one side modulated along the travel:
    ``1 + Σ a_k·cos(κ_k·x + φ_k)``; ``terms`` holds ``(a_k, κ_k in rad/m, φ_k in rad)``."""

    side: Side
    terms: tuple[tuple[float, float, float], ...]


def lead_periodic_friction(
    *,
    side: Side = "motor",
    lead_m: float,
    amplitudes: tuple[float, ...],
    phases_rad: tuple[float, ...],
) -> PositionFriction:
    """Friction periodic with the screw lead: harmonic ``k`` (1-based) of relative amplitude
    ``amplitudes[k-1]`` and phase ``phases_rad[k-1]``."""
    if len(amplitudes) != len(phases_rad):
        raise ValueError(
            f"phases_rad has {len(phases_rad)} entries; expected one per amplitude "
            f"({len(amplitudes)})"
        )
    if not (lead_m > 0 and math.isfinite(lead_m)):
        raise ValueError(f"lead_m = {lead_m} is invalid: expected a positive length in m")
    kappa = 2 * math.pi / lead_m
    return PositionFriction(
        side=side,
        terms=tuple(
            (float(a), kappa * (k + 1), float(p))
            for k, (a, p) in enumerate(zip(amplitudes, phases_rad, strict=True))
        ),
    )


def position_random_friction(
    *,
    side: Side = "table",
    rms: float,
    shortest_wavelength_m: float = 1e-3,
    longest_wavelength_m: float = 50e-3,
    n_terms: int = 16,
    seed: int = 0,
) -> PositionFriction:
    """A smooth seeded random friction profile along the travel: ``n_terms`` cosines with
    wavelengths log-spaced between the bounds, random phases and random (Rayleigh) amplitudes
    scaled so that the profile's RMS relative variation is ``rms``."""
    if not 0 <= rms <= 0.3:
        raise ValueError(f"rms = {rms} is invalid: expected a relative RMS in [0, 0.3]")
    if not 0 < shortest_wavelength_m < longest_wavelength_m:
        raise ValueError(
            f"shortest_wavelength_m = {shortest_wavelength_m} is invalid: expected "
            f"0 < shortest < longest_wavelength_m = {longest_wavelength_m}"
        )
    if not 1 <= n_terms <= 32:
        raise ValueError(f"n_terms = {n_terms} is invalid: expected an integer in [1, 32]")
    rng = np.random.default_rng(seed)
    lam = np.geomspace(shortest_wavelength_m, longest_wavelength_m, n_terms)
    amp = rng.rayleigh(1.0, n_terms)
    amp *= rms * math.sqrt(2.0) / float(np.sqrt(np.sum(amp**2)))
    phase = rng.uniform(0, 2 * math.pi, n_terms)
    return PositionFriction(
        side=side,
        terms=tuple(
            (float(a), float(2 * math.pi / lm), float(p))
            for a, lm, p in zip(amp, lam, phase, strict=True)
        ),
    )


@dataclass(frozen=True, slots=True, kw_only=True)
class StochasticFriction:
    """Trial-to-trial friction level factor (spread, distribution) and a within-trial
    Ornstein–Uhlenbeck fluctuation; both multiply every friction level. Seeded by the run's
    ``seed``."""

    level_spread: float = 0.0
    distribution: Literal["normal", "lognormal", "uniform"] = "lognormal"
    within_spread: float = 0.0
    correlation_time_s: float = 0.1


@dataclass(frozen=True, slots=True, kw_only=True)
class Backlash:
    """Gearhead backlash: a dead band of total width ``width_m`` (at the table) in the first
    link of the drive train, with contact stiffness and damping. ``initial_flank``, in
    [-1, 1]: where the drive side rests in the dead band when a run starts (+1 against the
    flank that pushes the table toward +x, as after a positive move; -1 the other; 0 the
    centre). None (the default): not known; a simulation starts at the centre, and a
    simulation compared with a measured trace (the diagnosis) starts against the flank
    that reproduces the trace better
    (:func:`nanostage.diagnosis.objective.simulate_readings_and_commands`)."""

    width_m: float = 20e-6
    contact_stiffness_n_per_m: float = 5e7
    damping_n_s_per_m: float = 2e3
    initial_flank: float | None = None


@dataclass(frozen=True, slots=True, kw_only=True)
class DriveCompliance:
    """Coupling (torsional) compliance as a table-equivalent spring between the motor side and
    the screw + table (two-mass); with ``axial_stiffness_n_per_m`` also the screw/nut axial
    spring between screw and table (three-mass)."""

    stiffness_n_per_m: float = 4.9e7
    damping_n_s_per_m: float = 2e3
    axial_stiffness_n_per_m: float | None = None
    axial_damping_n_s_per_m: float = 1e3


@dataclass(frozen=True, slots=True, kw_only=True)
class AmplifierDynamics:
    """First-order amplifier with bandwidth and slew-rate limit."""

    bandwidth_hz: float = 2e3
    slew_v_per_s: float = 1e5


@dataclass(frozen=True, slots=True, kw_only=True)
class EncoderErrors:
    """Encoder interpolation (cyclic) error and noise, added before the floor quantisation."""

    cyclic_amplitude_m: float = 0.0
    cyclic_period_m: float = 20e-6
    cyclic_phase_rad: float = 0.0
    noise_std_m: float = 0.0


@dataclass(frozen=True, slots=True, kw_only=True)
class Interferometer:
    """An interferometer channel on the true table position (recorded, not fed back)."""

    resolution_m: float = 1e-9
    noise_std_m: float = 0.0


@dataclass(frozen=True, slots=True, kw_only=True)
class Effects:
    """The effects switched on (all off by default).

    ``table_friction`` replaces the plant's table friction (the Dahl model of the seed);
    ``backlash`` sits in the first link of the drive train, which ``compliance`` (or, alone,
    the backlash's contact stiffness) makes a two- or three-mass chain.
    """

    table_friction: StaticFrictionMap | LuGre | Gms | None = None
    motor_friction: FrictionModifiers = field(default_factory=FrictionModifiers)
    position_friction: tuple[PositionFriction, ...] = ()
    stochastic: StochasticFriction | None = None
    backlash: Backlash | None = None
    compliance: DriveCompliance | None = None
    amplifier: AmplifierDynamics | None = None
    encoder_errors: EncoderErrors | None = None
    interferometer: Interferometer | None = None
    sensor_delay_samples: int = 0
    computation_delay_samples: int = 0
    jitter_s: float = 0.0


#: Every effect name, in documentation order.
EFFECT_NAMES: tuple[str, ...] = (
    # friction models on the table side (the nominal seed model uses Dahl)
    "coulomb_viscous",
    "stribeck",
    "dahl",
    "lugre",
    "gms",
    # friction phenomena
    "asymmetric_friction",
    "dwell_static_friction",
    "frictional_memory",
    "lead_periodic_friction",
    "position_random_friction",
    "stochastic_friction",
    # drive train
    "backlash",
    "drive_compliance",
    # drive electronics
    "motor_inductance",
    "amplifier_dynamics",
    "voltage_saturation",
    "dac_quantisation",
    # sensors
    "encoder_cyclic_error",
    "encoder_noise",
    "interferometer",
    "sensor_delay",
    # controller timing
    "computation_delay",
    "sample_jitter",
    # external and known inputs
    "offset_force",
    "force_disturbance",
    "command_disturbance",
)
