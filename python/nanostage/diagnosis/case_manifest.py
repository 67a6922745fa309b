"""The head of a benchmark case's manifest: the seed preset with its three uncertain friction
levels free, and the diagnosis over every candidate.

Shared by both truth families of the blind benchmark; it imports nothing of nanostage, so
the independent family stays free of the package's plant, friction and effect code.
"""

from __future__ import annotations

__all__ = ["case_manifest_head"]


def case_manifest_head(
    dahl_coulomb_force_n: float, static_torque_nm: float, coulomb_torque_nm: float, seed: int
) -> list[str]:
    """The manifest's ``[model]``, ``[model.bounds]`` and ``[diagnosis]`` lines (one per list
    item, ending with an empty line): the Dahl level and the motor map's static and Coulomb
    torques are free, within bounds around the given nominal values."""
    fc0, ts0, tc0 = dahl_coulomb_force_n, static_torque_nm, coulomb_torque_nm
    return [
        "[model]",
        'preset = "seed"',
        'free = ["plant.dahl.coulomb_force_n", "plant.motor_friction.static_torque_nm",',
        '        "plant.motor_friction.coulomb_torque_nm"]',
        "",
        "[model.bounds]",
        f'"plant.dahl.coulomb_force_n" = [{0.6 * fc0}, {1.5 * fc0}]',
        f'"plant.motor_friction.static_torque_nm" = [{0.8 * ts0}, {1.5 * ts0}]',
        f'"plant.motor_friction.coulomb_torque_nm" = [{0.7 * tc0}, {1.3 * tc0}]',
        "",
        "[diagnosis]",
        'candidates = "all"',
        f"seed = {seed}",
        "",
    ]
