"""Frozen, keyword-only configuration dataclasses with units in the field names.

Valid ranges are enforced by the Rust core (one definition, in ``rust/src``): a
:class:`Plant`, :class:`FpgaPid`, :class:`IntegratorOptions` or :class:`System` raises
:class:`nanostage.ConfigError` naming the field, the value and the valid range when it is
constructed, before anything runs. The block dataclasses (:class:`Motor`, ...) are checked
when they are assembled into a :class:`Plant`. A value of the wrong type (a string where a
:class:`Motor` or a float belongs) raises ``ConfigTypeError``, a :class:`nanostage.ConfigError`
that is also a :class:`TypeError`, naming the field path, the value, its type and the expected
type, e.g. ``motor = 'abc' (str) is invalid: expected a Motor``.
"""

from __future__ import annotations

import dataclasses
import difflib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

from . import _core
from .effects import Effects, StaticFrictionMap

Rounding = Literal["truncate", "half_up", "half_even"]
OverflowMode = Literal["saturate", "wrap"]
AntiWindup = Literal["none", "clamp", "conditional"]


@dataclass(frozen=True, slots=True, kw_only=True)
class Fxp:
    """A LabVIEW fixed-point format ⟨signed, word_bits, int_bits⟩ with rounding and overflow.

    ``frac_bits = word_bits - int_bits`` must lie in [-64, 64]; ``word_bits`` in [1, 64]
    (signed) or [1, 63] (unsigned).
    """

    signed: bool
    word_bits: int
    int_bits: int
    rounding: Rounding = "half_even"
    overflow: OverflowMode = "saturate"

    @property
    def frac_bits(self) -> int:
        """Fraction bits (``word_bits - int_bits``)."""
        return self.word_bits - self.int_bits

    def to_dict(self) -> dict[str, object]:
        """Plain dict (the form the independent reference model takes)."""
        return {
            "signed": self.signed,
            "word_bits": self.word_bits,
            "int_bits": self.int_bits,
            "rounding": self.rounding,
            "overflow": self.overflow,
        }


@dataclass(frozen=True, slots=True, kw_only=True)
class Motor:
    """DC motor: armature circuit and rotor. ``resistance_ohm`` in [1e-3, 1e3] Ω (1 mΩ is
    below any winding), ``inductance_h`` in [1e-9, 1] H (1 nH is a millimetre of wire),
    ``rotor_inertia_kg_m2`` in [1e-12, 1] kg·m² (a hundredth of the smallest micromotor)."""

    resistance_ohm: float
    inductance_h: float
    torque_constant_nm_per_a: float
    back_emf_v_s_per_rad: float
    rotor_inertia_kg_m2: float
    quasi_static_current: bool = False


@dataclass(frozen=True, slots=True, kw_only=True)
class StribeckFriction:
    """Stribeck torque on the motor shaft, with true stiction up to the static torque.
    ``stribeck_velocity_rad_per_s`` in [1e-3, 1e5] rad/s: far below a milliradian per second
    the Stribeck drop is a step the stick/slip logic cannot resolve."""

    static_torque_nm: float
    coulomb_torque_nm: float
    viscous_nm_s_per_rad: float
    stribeck_velocity_rad_per_s: float
    stribeck_exponent: float = 2.0


@dataclass(frozen=True, slots=True, kw_only=True)
class Gearhead:
    """Gearhead: ratio (motor turns per output turn, [1, 1e4]) and efficiency ([1e-3, 1])."""

    ratio: float
    efficiency: float


@dataclass(frozen=True, slots=True, kw_only=True)
class BallScrew:
    """Ball screw: lead per revolution ([1e-5, 0.1] m), efficiency ([1e-3, 1]), shaft inertia
    ([0, 1] kg·m², at least 1e-12 in a three-mass drive train)."""

    lead_m: float
    efficiency: float
    inertia_kg_m2: float = 0.0


@dataclass(frozen=True, slots=True, kw_only=True)
class Table:
    """Moving table: mass ([1e-6, 1e4] kg) and a constant external force opposing +x."""

    mass_kg: float
    external_force_n: float = 0.0


@dataclass(frozen=True, slots=True, kw_only=True)
class DahlFriction:
    """Dahl friction on the table side: Coulomb force, rest stiffness, shape exponent.
    ``coulomb_force_n`` in [1e-6, 1e5] N (a micronewton is below any guide's friction),
    ``stiffness_n_per_m`` in [1e-3, 1e12] N/m.

    ``asymmetry`` (a, in [-0.9, 0.9]) makes the Coulomb level depend on the direction of
    sliding: ``Fc·(1 + a·sgn v)``, so steady sliding gives ``Fc·(1 + a)`` in + and
    ``-Fc·(1 - a)`` in − (docs/effects.md). A plant with ``asymmetry != 0`` runs on the
    component plant; :func:`nanostage.simulate_plant` (the rigid plant alone) refuses it."""

    coulomb_force_n: float
    stiffness_n_per_m: float
    exponent: float = 1.0
    asymmetry: float = 0.0


@dataclass(frozen=True, slots=True, kw_only=True)
class Plant:
    """The rigid axis: motor → gearhead → ball screw → table, friction on both sides."""

    motor: Motor
    motor_friction: StribeckFriction
    gearhead: Gearhead
    screw: BallScrew
    table: Table
    dahl: DahlFriction

    def __post_init__(self) -> None:
        _core.validate_plant(self)

    @property
    def transmission_m_per_rad(self) -> float:
        """Table travel per motor radian, ``lead / (2π · ratio)``."""
        import math

        return self.screw.lead_m / (2.0 * math.pi * self.gearhead.ratio)


@dataclass(frozen=True, slots=True, kw_only=True)
class FpgaPid:
    """The FPGA position loop (docs/controller.md): gains, formats, range, units, timing.

    Gains are in *output units* per count (P), per count·sample (I) and per count of motion
    per sample (D, on the measurement with the damping sign). One output unit is
    ``output_unit_v`` volts at the amplifier input.
    """

    kp: float
    ki: float
    kd: float
    gain_format: Fxp
    measurement_format: Fxp
    error_format: Fxp
    term_format: Fxp
    integrator_format: Fxp
    output_format: Fxp
    dac_format: Fxp
    dac_scale_format: Fxp
    output_min: float
    output_max: float
    anti_windup: AntiWindup
    output_unit_v: float
    dac_lsb_v: float
    clock_hz: float = 40e6
    ticks_per_sample: int = 40_000
    latency_ticks: int = 0

    def __post_init__(self) -> None:
        _core.validate_controller(self)

    @property
    def sample_period_s(self) -> float:
        """Control period ``ticks_per_sample / clock_hz``."""
        return self.ticks_per_sample / self.clock_hz

    def to_dict(self) -> dict[str, object]:
        """Plain dict (formats as dicts), the form the independent reference model takes."""
        out: dict[str, object] = {}
        for name in self.__dataclass_fields__:
            v = getattr(self, name)
            out[name] = v.to_dict() if isinstance(v, Fxp) else v
        return out


@dataclass(frozen=True, slots=True, kw_only=True)
class ForceDrivePlant:
    """A force-controlled drive moving a lumped mass (EMPS): ``force = gain · command``,
    friction on the table as a static map with true stiction, a constant offset force.
    ``drive_mass_kg`` is the part of the mass on the drive side of a compliant link (it is
    lumped with ``mass_kg`` when the chain is rigid; at least 1e-6 kg with a link, and
    ``mass_kg`` at least 1e-6 kg, as :class:`Table`)."""

    drive_gain_n_per_v: float
    mass_kg: float
    friction: StaticFrictionMap
    external_force_n: float = 0.0
    drive_mass_kg: float = 0.0


@dataclass(frozen=True, slots=True, kw_only=True)
class CascadeController:
    """The floating-point cascade of a dSPACE drive (EMPS):
    ``u(k) = kp·kv·(r(k) − y(k)) − kv·(y(k) − y(k−2))/(2T)``, saturated at ±``saturation_v``."""

    kp_per_s: float
    kv_v_s_per_m: float
    sample_period_s: float = 1e-3
    saturation_v: float = 10.0


@dataclass(frozen=True, slots=True, kw_only=True)
class Encoder:
    """Linear incremental encoder: the size of one count and where it measures."""

    count_m: float = 100e-9
    side: Literal["table", "motor"] = "table"


@dataclass(frozen=True, slots=True, kw_only=True)
class OutputStage:
    """Analog output → amplifier: gain and voltage limit."""

    amplifier_gain: float = 1.0
    amplifier_limit_v: float = 6.0


@dataclass(frozen=True, slots=True, kw_only=True)
class IntegratorOptions:
    """RODAS4 options: tolerances, step bounds, event location, and the work budget of one
    control interval (from a sample to the output update, or from there to the next sample):
    at most ``max_steps`` integrator steps (accepted and rejected, in [10, 1e9]) and
    ``max_events`` stick/slip events (in [1, 1e9]). A run that needs more, e.g. a friction
    law switching between stick and slip faster than the model can resolve, ends with
    :class:`nanostage.SimulationError` naming the time, the state and the cause (a campaign
    trial: its failure status), so that no configuration can run for ever. The seed axis and
    the effect library take at most a few hundred steps and about ten events per interval."""

    rtol: float = 1e-6
    atol_position_m: float = 1e-11
    h_init_s: float = 1e-5
    h_min_s: float = 1e-14
    h_max_s: float = 1e-3
    max_steps: int = 100_000
    max_events: int = 10_000
    event_tol_s: float = 1e-11

    def __post_init__(self) -> None:
        _core.validate_integrator(self)


@dataclass(frozen=True, slots=True, kw_only=True)
class System:
    """Plant + controller + sensor + output stage + integrator: everything a run needs."""

    plant: Plant | ForceDrivePlant
    controller: FpgaPid | CascadeController
    encoder: Encoder = field(default_factory=Encoder)
    output_stage: OutputStage = field(default_factory=OutputStage)
    integrator: IntegratorOptions = field(default_factory=IntegratorOptions)
    effects: Effects = field(default_factory=Effects)

    def __post_init__(self) -> None:
        _core.validate_system(self)

    @property
    def sample_period_s(self) -> float:
        """Control period, s."""
        return self.controller.sample_period_s


# --------------------------------------------------------------------------------------------
# Dotted paths into the configuration dataclass tree
# --------------------------------------------------------------------------------------------


def did_you_mean(word: str, options: Sequence[str]) -> str:
    """`` (did you mean 'x'?)`` naming the closest of ``options`` to ``word``, or ``""``."""
    close = difflib.get_close_matches(word, list(options), n=1)
    return f" (did you mean {close[0]!r}?)" if close else ""


def get_path(obj: Any, path: str) -> Any:
    """The value at a dotted field path, e.g. ``get_path(system, "plant.dahl.exponent")``.

    Raises
    ------
    KeyError
        Naming the first component that is not a field, the fields there and a close match.
    """
    cur = obj
    done: list[str] = []
    for part in path.split("."):
        if not dataclasses.is_dataclass(cur) or isinstance(cur, type):
            where = ".".join(done)
            what = "is None (switched off in the preset)" if cur is None else "is a value"
            raise KeyError(f"{where!r} {what}, not a group of fields; {path!r} goes past it")
        names = [f.name for f in dataclasses.fields(cur)]
        if part not in names:
            where = ".".join(done) or "the model"
            raise KeyError(
                f"{where} ({type(cur).__name__}) has no field {part!r}{did_you_mean(part, names)}; "
                f"its fields are: {', '.join(names)}"
            )
        cur = getattr(cur, part)
        done.append(part)
    return cur


def replace_paths(obj: Any, values: Mapping[str, Any]) -> Any:
    """A copy of a frozen dataclass tree with the fields at dotted paths replaced.

    Each dataclass on a path is rebuilt with :func:`dataclasses.replace`, so its validation
    (``__post_init__``) runs again: invalid values raise the dataclass's error
    (:class:`nanostage.ConfigError` for the nanostage configuration).

    Parameters
    ----------
    obj : dataclass instance
        The root (e.g. a :class:`nanostage.System`).
    values : mapping of str to Any
        Dotted path → new value.
    """
    for path in values:
        get_path(obj, path)  # raise KeyError early for a bad path
    return _replace_checked(obj, values)


def _replace_checked(obj: Any, values: Mapping[str, Any]) -> Any:
    """:func:`replace_paths` once every path is known to exist (checked once, at the root:
    the diagnosis sets each experiment's controller on every model it simulates)."""
    grouped: dict[str, dict[str, Any]] = {}
    leaves: dict[str, Any] = {}
    for path, value in values.items():
        head, _, rest = path.partition(".")
        if rest:
            grouped.setdefault(head, {})[rest] = value
        else:
            leaves[head] = value
    changes = dict(leaves)
    for head, sub in grouped.items():
        changes[head] = _replace_checked(getattr(obj, head), sub)
    return dataclasses.replace(obj, **changes) if changes else obj


def field_paths(obj: Any, *, numeric_only: bool = True) -> tuple[str, ...]:
    """Every leaf field path of a dataclass tree (numeric leaves only by default)."""
    out: list[str] = []

    def walk(cur: Any, prefix: str) -> None:
        for f in dataclasses.fields(cur):
            v = getattr(cur, f.name)
            p = f"{prefix}{f.name}"
            if dataclasses.is_dataclass(v) and not isinstance(v, type):
                walk(v, p + ".")
            elif not numeric_only or (isinstance(v, int | float) and not isinstance(v, bool)):
                out.append(p)

    walk(obj, "")
    return tuple(out)
