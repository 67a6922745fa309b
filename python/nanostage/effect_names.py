"""The stable names of the effect library's components (the diagnosis refers to effects by
these names; they never change meaning). The components themselves and their parameters are
in :mod:`nanostage.effects`.
"""

from __future__ import annotations

__all__ = ["EFFECT_NAMES"]

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
