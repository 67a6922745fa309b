"""The head of a benchmark case's manifest: the seed preset with its uncertain parameters
free, and the diagnosis over every candidate.

Shared by both truth families of the blind benchmark; it imports nothing of nanostage, so
the independent family stays free of the package's plant, friction and effect code.
"""

from __future__ import annotations

from collections.abc import Mapping

__all__ = ["UNCERTAIN_MOTOR_AND_INERTIA", "case_manifest_head"]

#: Free parameters beyond the three friction levels, with bounds relative to the nominal
#: value, for a case whose nominal motor constants, inertia, viscous friction, Stribeck
#: velocity and presliding stiffness are uncertain too (datasheet tolerances of a small DC
#: motor are ±10 % on the motor constant and resistance; inertia and friction coefficients
#: are rarely known better than ±30 %). A free torque constant carries the back-EMF
#: constant with it (in SI units they are one motor constant; ``nanostage.diagnosis.run``).
UNCERTAIN_MOTOR_AND_INERTIA: Mapping[str, tuple[float, float]] = {
    "plant.motor.torque_constant_nm_per_a": (0.75, 1.25),
    "plant.motor.resistance_ohm": (0.75, 1.25),
    "plant.motor.rotor_inertia_kg_m2": (0.6, 1.5),
    "plant.motor_friction.viscous_nm_s_per_rad": (0.2, 5.0),
    "plant.motor_friction.stribeck_velocity_rad_per_s": (0.4, 2.5),
    "plant.dahl.stiffness_n_per_m": (0.5, 2.0),
}


def case_manifest_head(
    dahl_coulomb_force_n: float,
    static_torque_nm: float,
    coulomb_torque_nm: float,
    seed: int,
    *,
    also_free: Mapping[str, tuple[float, float, float]] | None = None,
    level_scatter: float | None = None,
) -> list[str]:
    """The manifest's ``[model]``, ``[model.bounds]`` and ``[diagnosis]`` lines (one per list
    item, ending with an empty line): the Dahl level and the motor map's static and Coulomb
    torques are free, within bounds around the given nominal values; ``also_free`` adds
    ``path → (nominal value, lower factor, upper factor)``; ``level_scatter``, unless None, is
    written as the diagnosis's run-to-run friction level scatter (relative, 1σ; 0: left
    out; None: not written, the diagnosis's default applies)."""
    fc0, ts0, tc0 = dahl_coulomb_force_n, static_torque_nm, coulomb_torque_nm
    bounds = {
        "plant.dahl.coulomb_force_n": (0.6 * fc0, 1.5 * fc0),
        "plant.motor_friction.static_torque_nm": (0.8 * ts0, 1.5 * ts0),
        "plant.motor_friction.coulomb_torque_nm": (0.7 * tc0, 1.3 * tc0),
    }
    for path, (v, lo, hi) in (also_free or {}).items():
        bounds[path] = (lo * v, hi * v)
    paths = [f'"{p}"' for p in bounds]
    free = ",\n        ".join(", ".join(paths[i : i + 2]) for i in range(0, len(paths), 2))
    return [
        "[model]",
        'preset = "seed"',
        *f"free = [{free}]".split("\n"),
        "",
        "[model.bounds]",
        *(f'"{p}" = [{lo}, {hi}]' for p, (lo, hi) in bounds.items()),
        "",
        "[diagnosis]",
        'candidates = "all"',
        f"seed = {seed}",
        *([] if level_scatter is None else [f"level_scatter = {float(level_scatter)!r}"]),
        "",
    ]
