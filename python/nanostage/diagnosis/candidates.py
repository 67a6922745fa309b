"""Candidate effects for the gap diagnosis: for each effect name of the effect library, how
to add it to a nominal :class:`~nanostage.System` with a vector of physical parameters, the
parameters' bounds and start values, and the signature it leaves in a response.

Every candidate works on the nominal model as given: it *adds* one effect (or, for the
friction-model candidates, *replaces* the table friction model). Parameters are fitted in a
normalised coordinate (linear or logarithmic between the bounds).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

from ..config import ForceDrivePlant, FpgaPid, Plant, System
from ..effects import (
    EFFECT_NAMES,
    AmplifierDynamics,
    Backlash,
    DriveCompliance,
    DwellStaticFriction,
    EncoderErrors,
    Gms,
    LuGre,
    PositionFriction,
    StaticFrictionMap,
)
from ..fitting import Param, harmonic, lugre_model, static_map

__all__ = [
    "CANDIDATES",
    "NOT_CANDIDATES",
    "Candidate",
    "Param",
    "applicable_candidates",
]


Apply = Callable[[System, Sequence[float]], System]


@dataclass(frozen=True, slots=True, kw_only=True)
class Candidate:
    """A candidate effect: its stable name, parameters, how it augments a system, and the
    signature it leaves in a response (in words, for the report)."""

    name: str
    params: tuple[Param, ...]
    apply: Apply
    signature: str
    #: Integer settings tried one by one instead of fitted (delays), else empty.
    discrete: tuple[int, ...] = ()
    #: Points of the global scan before the local fits, where the default
    #: (:attr:`DiagnosisSettings.scan_points` per parameter) is too coarse for a rugged gap.
    scan_points: int | None = None
    #: Local fits started from the best points of that scan (in addition to the starts the
    #: engine gives), for a gap whose basin is narrow enough that the single best scanned
    #: point may lie outside it.
    scan_starts: int = 1
    #: Names of the parameters the coarse scan draws (the others keep their start values
    #: during the scan; the local fits free them all); empty: every parameter. A table law
    #: that falls with speed has its level and presliding stiffness pinned by the slews and
    #: micro-steps, and a shape (the excess at rest, the speed it fades over) that is
    #: unknown over decades: its scan spends its points on the shape.
    scan_only: tuple[str, ...] = ()


def _fx(system: System, **changes: object) -> System:
    return replace(system, effects=replace(system.effects, **changes))  # type: ignore[arg-type]


def _table_levels(system: System) -> tuple[float, float]:
    """(Coulomb, static) force level of the table-side friction of the nominal model, N;
    10 N for a model without Coulomb friction (a scale for the candidates' bounds)."""
    fc, fs = _raw_table_levels(system)
    if fc <= 0.0:
        return 10.0, max(fs, 10.0)
    return fc, fs


def _raw_table_levels(system: System) -> tuple[float, float]:
    tf = system.effects.table_friction
    if isinstance(tf, StaticFrictionMap | LuGre | Gms):
        return tf.coulomb_force_n, tf.static_force_n
    p = system.plant
    if isinstance(p, ForceDrivePlant):
        return p.friction.coulomb_force_n, p.friction.static_force_n
    return p.dahl.coulomb_force_n, p.dahl.coulomb_force_n


def _presliding_stiffness(system: System) -> float:
    p = system.plant
    if isinstance(p, Plant):
        return p.dahl.stiffness_n_per_m
    return 1e7


def _static_side(system: System) -> str:
    """Which side carries the nominal model's static map (where stiction acts)."""
    return "motor" if isinstance(system.plant, Plant) else "table"


def _modify_static(system: System, **changes: object) -> System:
    """Apply modifiers to the model's static map where stiction acts: a table map set in the
    effects (e.g. by a selected friction-model candidate), else the motor map of the seed or
    the friction map of a force drive."""
    tf = system.effects.table_friction
    if isinstance(tf, StaticFrictionMap):
        return _fx(system, table_friction=replace(tf, **changes))  # type: ignore[arg-type]
    p = system.plant
    if isinstance(p, Plant):
        if "viscous_asymmetry" in changes:
            changes = {k: v for k, v in changes.items() if k != "viscous_asymmetry"}
        mods = replace(system.effects.motor_friction, **changes)  # type: ignore[arg-type]
        return _fx(system, motor_friction=mods)
    friction = replace(p.friction, **changes)  # type: ignore[arg-type]
    return replace(system, plant=replace(p, friction=friction))


def _with_table_asymmetry(system: System, asymmetry: float) -> System:
    """``system`` with the direction asymmetry of its table friction law set: a LuGre or GMS
    table friction of the effects, else the Dahl law of a seed plant. A static table map
    (where :func:`_modify_static` acts) and a force drive's map are left as they are."""
    tf = system.effects.table_friction
    if isinstance(tf, LuGre | Gms):
        return _fx(system, table_friction=replace(tf, asymmetry=asymmetry))
    p = system.plant
    if tf is None and isinstance(p, Plant):
        return replace(system, plant=replace(p, dahl=replace(p.dahl, asymmetry=asymmetry)))
    return system


def _static_value(system: System, name: str) -> float:
    """The modifier ``name`` of the static map where stiction acts, as
    :func:`_modify_static` would set it (0 where it sets nothing)."""
    tf = system.effects.table_friction
    if isinstance(tf, StaticFrictionMap):
        return float(getattr(tf, name))
    p = system.plant
    if isinstance(p, Plant):
        return (
            0.0
            if name == "viscous_asymmetry"
            else float(getattr(system.effects.motor_friction, name))
        )
    return float(getattr(p.friction, name))


def _table_asymmetry(system: System) -> float:
    """The direction asymmetry of the table law :func:`_with_table_asymmetry` sets (0 where
    it sets none)."""
    tf = system.effects.table_friction
    if isinstance(tf, LuGre | Gms):
        return tf.asymmetry
    p = system.plant
    if tf is None and isinstance(p, Plant):
        return p.dahl.asymmetry
    return 0.0


def _null(value: float, lower: float, upper: float) -> float | None:
    """``value`` as a parameter's null (:attr:`Param.null`: the model's own value, where the
    candidate adds nothing) if it lies within the bounds, else None (no test)."""
    return value if lower <= value <= upper else None


def _asymmetry_param(name: str, own: float) -> Param:
    """A direction asymmetry in [−0.6, 0.6], from 0, whose null is the model's ``own``."""
    return Param(
        name=name, unit="-", lower=-0.6, upper=0.6, initial=0.0, null=_null(own, -0.6, 0.6)
    )


def _limit_param(name: str, lim: float) -> Param:
    """A voltage limit from 0.3 to 2 times the model's ``lim``, from and null at it."""
    return Param(name=name, unit="V", lower=0.3 * lim, upper=2 * lim, initial=lim, null=lim)


def _offset_param(own: float, fc: float) -> Param:
    """An offset force within ±``fc``, from 0, whose null is the model's ``own``."""
    return Param(
        name="external_force_n",
        unit="N",
        lower=-fc,
        upper=fc,
        initial=0.0,
        null=_null(own, -fc, fc),
    )


def _with_plant(system: System, change: Callable[[Any], Any]) -> System:
    """``system`` with ``change`` applied to *its own* plant. A candidate's ``apply`` must
    start from the system it is given (which carries the fitted free parameters), never from
    the nominal plant the candidate was made from."""
    return replace(system, plant=change(system.plant))


def _lead_m(system: System) -> float:
    p = system.plant
    return p.screw.lead_m if isinstance(p, Plant) else 2.5e-3


def _add_position_term(system: System, pf: PositionFriction) -> System:
    return _fx(system, position_friction=(*system.effects.position_friction, pf))


def _link_params(*, lower_n_per_m: float, initial_n_per_m: float) -> tuple[Param, Param]:
    """Stiffness (up to 1e9 N/m) and damping of a drive-train link, log-scaled."""
    return (
        Param(
            name="stiffness_n_per_m",
            unit="N/m",
            lower=lower_n_per_m,
            upper=1e9,
            initial=initial_n_per_m,
            log=True,
        ),
        Param(name="damping_n_s_per_m", unit="N·s/m", lower=1.0, upper=1e5, initial=1e3, log=True),
    )


def _presliding_params(sys: System) -> tuple[Param, ...]:
    """Coulomb force, static excess, presliding stiffness and Stribeck velocity, with bounds
    scaled from the nominal model (the parameters of the LuGre and GMS candidates)."""
    fc, _ = _table_levels(sys)
    k = _presliding_stiffness(sys)
    return (
        Param(name="coulomb_force_n", unit="N", lower=0.1 * fc, upper=3 * fc, initial=fc),
        Param(
            name="static_excess_n",
            unit="N",
            lower=0.01 * fc,
            upper=2 * fc,
            initial=0.3 * fc,
            log=True,
        ),
        Param(
            name="stiffness_n_per_m", unit="N/m", lower=k / 100, upper=k * 100, initial=k, log=True
        ),
        Param(
            name="stribeck_velocity_m_per_s",
            unit="m/s",
            lower=1e-5,
            upper=1e-2,
            initial=5e-4,
            log=True,
        ),
    )


#: The shape of a Stribeck fall (excess at rest, the speed it fades over): what the scan of a
#: table law that falls with speed draws (:attr:`Candidate.scan_only`).
_STRIBECK_SHAPE = ("static_excess_n", "stribeck_velocity_m_per_s")


def _build() -> dict[str, Callable[[System], Candidate | str]]:
    """Factories: nominal system → candidate, or the reason it does not apply."""

    def coulomb_viscous(sys: System) -> Candidate | str:
        fc, _ = _table_levels(sys)
        return Candidate(
            name="coulomb_viscous",
            params=(
                Param(name="coulomb_force_n", unit="N", lower=0.1 * fc, upper=3 * fc, initial=fc),
                Param(
                    name="viscous_n_s_per_m",
                    unit="N·s/m",
                    lower=1.0,
                    upper=1e5,
                    initial=100.0,
                    log=True,
                ),
            ),
            apply=lambda s, v: _fx(s, table_friction=static_map(v[0], 0.0, v[1])),
            signature="rate-independent sliding friction with true stiction: final errors "
            "(stick before the target) and a speed-dependent slew",
        )

    def stribeck(sys: System) -> Candidate | str:
        fc, _ = _table_levels(sys)
        return Candidate(
            name="stribeck",
            params=(
                Param(name="coulomb_force_n", unit="N", lower=0.1 * fc, upper=3 * fc, initial=fc),
                Param(
                    name="static_excess_n",
                    unit="N",
                    lower=0.01 * fc,
                    upper=2 * fc,
                    initial=0.3 * fc,
                    log=True,
                ),
                Param(
                    name="stribeck_velocity_m_per_s",
                    unit="m/s",
                    lower=1e-5,
                    upper=1e-2,
                    initial=5e-4,
                    log=True,
                ),
            ),
            apply=lambda s, v: _fx(s, table_friction=static_map(v[0], v[1], 0.0, v[2])),
            signature="friction falling with speed at low velocity: a breakaway jump at the "
            "start of moves and stick-slip while settling",
            scan_only=_STRIBECK_SHAPE,
            scan_starts=3,
        )

    def dahl(sys: System) -> Candidate | str:
        if isinstance(sys.plant, Plant) and sys.effects.table_friction is None:
            return "the nominal model already uses Dahl friction on the table"
        if isinstance(sys.plant, ForceDrivePlant):
            return "Dahl on a force drive is not offered; LuGre with σ1 = 0 and Fs = Fc covers it"
        fc, _ = _table_levels(sys)
        k = _presliding_stiffness(sys)
        return Candidate(
            name="dahl",
            params=(
                Param(name="coulomb_force_n", unit="N", lower=0.1 * fc, upper=3 * fc, initial=fc),
                Param(
                    name="stiffness_n_per_m",
                    unit="N/m",
                    lower=k / 100,
                    upper=k * 100,
                    initial=k,
                    log=True,
                ),
            ),
            apply=lambda s, v: _dahl(s, v),
            signature="presliding spring with rate-independent hysteresis: rounded start and "
            "end of moves, sub-count creep after reversals",
        )

    def lugre(sys: System) -> Candidate | str:
        return Candidate(
            name="lugre",
            params=_presliding_params(sys),
            apply=lambda s, v: _fx(
                s,
                table_friction=lugre_model(
                    stiffness_n_per_m=v[2],
                    damping_n_s_per_m=0.0,
                    viscous_n_s_per_m=0.0,
                    coulomb_force_n=v[0],
                    static_excess_n=v[1],
                    stribeck_velocity_m_per_s=v[3],
                ),
            ),
            signature="presliding spring plus a Stribeck curve: breakaway overshoot of the "
            "friction force and hysteresis in presliding",
            scan_only=_STRIBECK_SHAPE,
            scan_starts=3,
        )

    def gms(sys: System) -> Candidate | str:
        return Candidate(
            name="gms",
            params=(
                *_presliding_params(sys),
                Param(
                    name="presliding_spread",
                    unit="-",
                    lower=1.0,
                    upper=1000.0,
                    initial=GMS_SPREAD_INITIAL,
                    log=True,
                ),
            ),
            apply=lambda s, v: _fx(
                s, table_friction=gms_spread(v[0], v[0] + v[1], v[2], v[3], v[4])
            ),
            signature="Maxwell-slip presliding with non-local memory: hysteresis that depends "
            "on the reversal history, a presliding curve that bends over a range of "
            "displacements, plus a Stribeck curve",
            scan_only=(*_STRIBECK_SHAPE, "presliding_spread"),
            scan_starts=3,
        )

    def asymmetric(sys: System) -> Candidate | str:
        signature = (
            "different friction in + and − moves: direction-dependent slew speed, "
            "overshoot and final error"
        )
        if isinstance(sys.plant, ForceDrivePlant) or isinstance(
            sys.effects.table_friction, StaticFrictionMap
        ):
            return Candidate(
                name="asymmetric_friction",
                params=(
                    _asymmetry_param("asymmetry", _static_value(sys, "asymmetry")),
                    _asymmetry_param("viscous_asymmetry", _static_value(sys, "viscous_asymmetry")),
                ),
                apply=lambda s, v: _modify_static(s, asymmetry=v[0], viscous_asymmetry=v[1]),
                signature=signature,
            )
        # The seed: an asymmetry of the motor map and one of the table law (the Dahl of the
        # plant, or a LuGre or GMS set in the effects), each its own: where it sits, and how
        # much on each side, is unknown. While sliding they act together (a bias of
        # a_m·F_m + a_t·F_t); the breakaway and presliding tell the sides apart, and where
        # the data do not, the Occam factor counts the unconstrained direction as free.
        return Candidate(
            name="asymmetric_friction",
            params=(
                _asymmetry_param("asymmetry", _static_value(sys, "asymmetry")),
                _asymmetry_param("table_asymmetry", _table_asymmetry(sys)),
            ),
            apply=lambda s, v: _with_table_asymmetry(_modify_static(s, asymmetry=v[0]), v[1]),
            signature=signature,
        )

    def dwell(sys: System) -> Candidate | str:
        _fc, fs = _table_levels(sys)
        base = fs if isinstance(sys.plant, ForceDrivePlant) else motor_static_force_n(sys)
        return Candidate(
            name="dwell_static_friction",
            params=(
                Param(
                    name="rise_n",
                    unit="N",
                    lower=0.01 * base,
                    upper=10 * base,
                    initial=0.3 * base,
                    log=True,
                ),
                Param(
                    name="time_constant_s", unit="s", lower=1e-3, upper=10.0, initial=0.1, log=True
                ),
            ),
            apply=lambda s, v: _modify_static(
                s, dwell=DwellStaticFriction(rise_n=v[0], time_constant_s=v[1])
            ),
            signature="breakaway force growing with the rest time before a move: a later "
            "start after long dwells",
            # The gap of a dwell model is a narrow valley in (rise, time constant): too
            # little rise changes nothing, too much delays every breakaway far too long.
            # Each point costs one simulation of the short training set.
            # On a seed-16 case (rise 14 N, 0.35 s) the fit from the best of 128 scanned
            # points ended at 0.96 s (training gap 45 nm, not significant), from the best
            # three at 38 N and 4.4 s (38 nm), from the best four of 256 at the truth's
            # basin (13.6 N, 0.34 s, 33 nm, 25 % shrink, significant).
            scan_points=256,
            scan_starts=4,
        )

    def memory(sys: System) -> Candidate | str:
        return Candidate(
            name="frictional_memory",
            params=(
                Param(name="memory_lag_s", unit="s", lower=1e-4, upper=0.1, initial=5e-3, log=True),
            ),
            apply=lambda s, v: _modify_static(s, memory_lag_s=v[0]),
            signature="sliding friction lagging the velocity: different friction on "
            "acceleration and braking at the same speed",
        )

    def lead(sys: System) -> Candidate | str:
        lead_m = _lead_m(sys)
        side = _static_side(sys)
        kappa = 2 * math.pi / lead_m
        return Candidate(
            name="lead_periodic_friction",
            params=(
                Param(
                    name="cos_amplitude", unit="-", lower=-0.4, upper=0.4, initial=0.05, null=0.0
                ),
                Param(
                    name="sin_amplitude", unit="-", lower=-0.4, upper=0.4, initial=0.05, null=0.0
                ),
            ),
            apply=lambda s, v: _add_position_term(
                s,
                PositionFriction(side=side, terms=(harmonic(kappa, v[0], v[1]),)),  # type: ignore[arg-type]
            ),
            signature=f"friction periodic in position with the screw lead ({lead_m * 1e3:g} "
            "mm): a residual peak at the lead's spatial period",
        )

    def position_random(sys: System) -> Candidate | str:
        side = _static_side(sys)
        wavelengths = (40e-3, 20e-3, 10e-3)
        params: list[Param] = []
        for lam in wavelengths:
            for part in ("cos", "sin"):
                params.append(
                    Param(
                        name=f"{part}_{lam * 1e3:g}mm",
                        unit="-",
                        lower=-0.15,
                        upper=0.15,
                        initial=0.02,
                        null=0.0,
                    )
                )

        def apply(s: System, v: Sequence[float]) -> System:
            terms = tuple(
                harmonic(2 * math.pi / lam, v[2 * i], v[2 * i + 1])
                for i, lam in enumerate(wavelengths)
            )
            return _add_position_term(s, PositionFriction(side=side, terms=terms))  # type: ignore[arg-type]

        return Candidate(
            name="position_random_friction",
            params=tuple(params),
            apply=apply,
            signature="friction varying smoothly along the travel: final errors and slew "
            "speed depending on where the move happens",
        )

    def backlash(sys: System) -> Candidate | str:
        if not isinstance(sys.plant, Plant):
            return "a force drive has no gearhead"
        return Candidate(
            name="backlash",
            params=(
                Param(name="width_m", unit="m", lower=1e-7, upper=1e-4, initial=5e-6, log=True),
                Param(
                    name="contact_stiffness_n_per_m",
                    unit="N/m",
                    lower=1e6,
                    upper=1e9,
                    initial=5e7,
                    log=True,
                ),
            ),
            apply=lambda s, v: _fx(
                s, backlash=Backlash(width_m=v[0], contact_stiffness_n_per_m=v[1])
            ),
            signature="a dead band on reversal: lost motion after a change of direction and "
            "limit cycles around the target",
        )

    def compliance(sys: System) -> Candidate | str:
        signature = (
            "a drive-train resonance: ringing at a frequency set by the stiffness and the "
            "two masses"
        )
        p = sys.plant
        if isinstance(p, ForceDrivePlant):
            total = p.mass_kg

            def apply_force(s: System, v: Sequence[float]) -> System:
                # The drive-side mass is added as a ratio of the table-side mass, which stays
                # the plant's ``mass_kg`` (so a free nominal mass keeps its meaning).
                q = s.plant
                assert isinstance(q, ForceDrivePlant)
                plant = replace(q, drive_mass_kg=v[2] * q.mass_kg)
                return _fx(
                    replace(s, plant=plant),
                    compliance=DriveCompliance(stiffness_n_per_m=v[0], damping_n_s_per_m=v[1]),
                )

            return Candidate(
                name="drive_compliance",
                params=(
                    *_link_params(lower_n_per_m=1e4, initial_n_per_m=1e6),
                    Param(
                        name="drive_mass_ratio",
                        unit="-",
                        lower=0.02,
                        upper=2.0,
                        initial=0.3,
                        log=True,
                    ),
                ),
                apply=apply_force,
                signature=signature + f" (drive-side mass as a ratio of the {total:.4g} kg table)",
            )
        return Candidate(
            name="drive_compliance",
            params=_link_params(lower_n_per_m=1e5, initial_n_per_m=5e7),
            apply=lambda s, v: _fx(
                s, compliance=DriveCompliance(stiffness_n_per_m=v[0], damping_n_s_per_m=v[1])
            ),
            signature=signature,
        )

    def inductance(sys: System) -> Candidate | str:
        p = sys.plant
        if not isinstance(p, Plant):
            return "a force drive has no motor electrics"
        if not p.motor.quasi_static_current:
            return "the nominal model already includes the motor inductance"
        return Candidate(
            name="motor_inductance",
            params=(),
            apply=lambda s, v: _with_plant(
                s, lambda q: replace(q, motor=replace(q.motor, quasi_static_current=False))
            ),
            signature="a lag of the motor current behind the voltage (electrical pole)",
        )

    def amplifier(sys: System) -> Candidate | str:
        return Candidate(
            name="amplifier_dynamics",
            params=(
                Param(
                    name="bandwidth_hz", unit="Hz", lower=5.0, upper=5e3, initial=300.0, log=True
                ),
            ),
            apply=lambda s, v: _fx(
                s, amplifier=AmplifierDynamics(bandwidth_hz=v[0], slew_v_per_s=1e9)
            ),
            signature="a lag of the drive behind the command: slower starts and larger overshoot",
        )

    def saturation(sys: System) -> Candidate | str:
        ctl = sys.controller
        if isinstance(ctl, FpgaPid):
            lim = sys.output_stage.amplifier_limit_v
            return Candidate(
                name="voltage_saturation",
                params=(_limit_param("amplifier_limit_v", lim),),
                apply=lambda s, v: replace(
                    s, output_stage=replace(s.output_stage, amplifier_limit_v=v[0])
                ),
                signature="the slew speed at the voltage limit: the constant-slope ramp of "
                "large steps",
            )
        lim = ctl.saturation_v
        return Candidate(
            name="voltage_saturation",
            params=(_limit_param("saturation_v", lim),),
            apply=lambda s, v: replace(s, controller=replace(ctl, saturation_v=v[0])),
            signature="the command limit: the slope of the response while saturated",
        )

    def cyclic(sys: System) -> Candidate | str:
        period = 20e-6 if isinstance(sys.plant, Plant) else 2.5e-3 / 50_000 * 4
        return Candidate(
            name="encoder_cyclic_error",
            params=(
                Param(
                    name="cyclic_amplitude_m",
                    unit="m",
                    lower=1e-9,
                    upper=1e-6,
                    initial=5e-8,
                    log=True,
                ),
                Param(
                    name="cyclic_phase_rad", unit="rad", lower=-math.pi, upper=math.pi, initial=0.0
                ),
            ),
            apply=lambda s, v: _fx(
                s,
                encoder_errors=EncoderErrors(
                    cyclic_amplitude_m=v[0], cyclic_period_m=period, cyclic_phase_rad=v[1]
                ),
            ),
            signature=f"a reading error periodic with the scale's signal period "
            f"({period * 1e6:g} µm): final errors that repeat with position",
        )

    def delay(name: str, field: str, what: str) -> Callable[[System], Candidate]:
        def make(sys: System) -> Candidate:
            own = int(getattr(sys.effects, field))
            # Samples added to the model's own delay; −1 removes one the model assumes.
            changes = tuple(k for k in (-1, 1, 2, 3) if own + k >= 0)
            return Candidate(
                name=name,
                params=(),
                apply=lambda s, v: _fx(s, **{field: getattr(s.effects, field) + int(v[0])}),
                signature=what,
                discrete=changes,
            )

        return make

    def offset(sys: System) -> Candidate | str:
        p = sys.plant
        fc, _ = _table_levels(sys)
        if isinstance(p, Plant):
            return Candidate(
                name="offset_force",
                params=(_offset_param(p.table.external_force_n, fc),),
                apply=lambda s, v: _with_plant(
                    s, lambda q: replace(q, table=replace(q.table, external_force_n=v[0]))
                ),
                signature="a constant force along the axis (cable, gravity): + and − moves "
                "differ by a constant force",
            )
        return Candidate(
            name="offset_force",
            params=(_offset_param(p.external_force_n, fc),),
            apply=lambda s, v: _with_plant(s, lambda q: replace(q, external_force_n=v[0])),
            signature="a constant force along the axis: + and − moves differ by a constant force",
        )

    return {
        "coulomb_viscous": coulomb_viscous,
        "stribeck": stribeck,
        "dahl": dahl,
        "lugre": lugre,
        "gms": gms,
        "asymmetric_friction": asymmetric,
        "dwell_static_friction": dwell,
        "frictional_memory": memory,
        "lead_periodic_friction": lead,
        "position_random_friction": position_random,
        "backlash": backlash,
        "drive_compliance": compliance,
        "motor_inductance": inductance,
        "amplifier_dynamics": amplifier,
        "voltage_saturation": saturation,
        "encoder_cyclic_error": cyclic,
        "sensor_delay": delay(
            "sensor_delay",
            "sensor_delay_samples",
            "the controller acting on an older reading: more overshoot, lower damping",
        ),
        "computation_delay": delay(
            "computation_delay",
            "computation_delay_samples",
            "the command reaching the drive later: a delayed start and more overshoot",
        ),
        "offset_force": offset,
    }


def motor_static_force_n(sys: System) -> float:
    """The motor map's static torque as a force at the table (through the transmission and
    its efficiencies), N."""
    p = sys.plant
    assert isinstance(p, Plant)
    r = p.transmission_m_per_rad
    eta = p.gearhead.efficiency * p.screw.efficiency
    return eta * p.motor_friction.static_torque_nm / r


def _dahl(s: System, v: Sequence[float]) -> System:
    p = s.plant
    if isinstance(p, Plant):
        return _fx(
            replace(
                s,
                plant=replace(
                    p,
                    dahl=replace(p.dahl, coulomb_force_n=v[0], stiffness_n_per_m=v[1]),
                ),
            ),
            table_friction=None,
        )
    raise ValueError("Dahl as the table friction of a force drive is not supported")


#: Initial spread of the GMS candidate's element slip displacements (about the spread of the
#: fixed 0.5/0.3/0.2-weight shape it replaced).
GMS_SPREAD_INITIAL = 4.0


def gms_spread(
    coulomb_force_n: float,
    static_force_n: float,
    stiffness_n_per_m: float,
    vs: float,
    spread: float,
    n: int = 3,
) -> Gms:
    """An ``n``-element GMS of equal weights whose elements start to slip (at the Coulomb
    level) after displacements spread geometrically over the factor ``spread`` (element
    ``i`` at ``spread^(i/(n−1))`` times the first's): the total presliding stiffness
    ``stiffness_n_per_m`` at the origin, a presliding curve that bends over the range of
    displacements ``spread`` sets (1: one element's sharp corner; 100: a gradual curve)."""
    if not (spread >= 1.0 and math.isfinite(spread)):
        raise ValueError(f"presliding_spread = {spread} is invalid: expected a factor ≥ 1")
    if n < 2:
        raise ValueError(f"n = {n} is invalid: expected at least 2 elements")
    compliance = [spread ** (i / (n - 1)) for i in range(n)]  # element i: k_i ∝ 1/that
    total = sum(1.0 / c for c in compliance)
    return Gms(
        stiffness_n_per_m=tuple(stiffness_n_per_m / (c * total) for c in compliance),
        weights=tuple([1.0 / n] * n),
        coulomb_force_n=coulomb_force_n,
        static_force_n=static_force_n,
        stribeck_velocity_m_per_s=vs,
    )


_FACTORIES = _build()

#: Effects that are not fitted as candidates, with the reason (reported).
NOT_CANDIDATES: dict[str, str] = {
    "stochastic_friction": "random from trial to trial: it sets the noise floor (estimated "
    "from the spread of repeated experiments) rather than a deterministic gap",
    "encoder_noise": "random: part of the noise floor",
    "sample_jitter": "random: part of the noise floor",
    "interferometer": "a measurement channel, not an effect on the motion",
    "dac_quantisation": "always modelled (the FPGA loop is bit-exact)",
    "force_disturbance": "a known input: applied from the trace's disturbance_n column",
    "command_disturbance": "a known input: applied from the trace's disturbance_v column",
}

#: Every candidate name.
CANDIDATES: tuple[str, ...] = tuple(_FACTORIES)

assert set(CANDIDATES) | set(NOT_CANDIDATES) == set(EFFECT_NAMES), "registry out of date"


def applicable_candidates(
    system: System, names: Sequence[str] | None = None
) -> tuple[list[Candidate], dict[str, str]]:
    """The candidates that apply to ``system`` (default: all), and the skipped ones with the
    reason. Unknown names raise ``ValueError`` listing the valid ones."""
    chosen = list(CANDIDATES) if names is None else list(names)
    out: list[Candidate] = []
    skipped: dict[str, str] = {}
    for n in chosen:
        if n in NOT_CANDIDATES:
            skipped[n] = NOT_CANDIDATES[n]
            continue
        if n not in _FACTORIES:
            raise ValueError(f"unknown effect {n!r}; valid: {', '.join(EFFECT_NAMES)}")
        c = _FACTORIES[n](system)
        if isinstance(c, str):
            skipped[n] = c
        else:
            out.append(c)
    return out, skipped
