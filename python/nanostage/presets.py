"""Presets: the seed axis of the paper, with each value's unit, source and confidence.

The numbers come from the Rust core (``_core.seed_values()``), so Rust benches/tests and
Python use one set. Confidence tags follow DOMAIN.md: ``B`` stated in the seed paper,
``I`` derived here (arithmetic shown), ``U`` uncertain planning value, ``K`` textbook.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from types import MappingProxyType
from typing import Any, Final

from . import _core
from .config import (
    BallScrew,
    CascadeController,
    DahlFriction,
    Encoder,
    ForceDrivePlant,
    FpgaPid,
    Fxp,
    Gearhead,
    IntegratorOptions,
    Motor,
    OutputStage,
    Plant,
    StribeckFriction,
    System,
    Table,
)
from .effects import Effects, StaticFrictionMap

__all__ = [
    "PRESETS",
    "PRESET_CONTROLLER_KIND",
    "PRESET_TRAVEL_M",
    "SEED_PROVENANCE",
    "Provenance",
    "preset_names",
    "preset_system",
    "seed",
    "seed_controller",
    "seed_plant",
    "table1_gains",
    "table1_system",
]


@dataclass(frozen=True, slots=True, kw_only=True)
class Provenance:
    """Where a preset value comes from."""

    unit: str
    source: str
    confidence: str


_P = Provenance
#: Unit, source and confidence of every seed value, keyed by dotted field path.
SEED_PROVENANCE: dict[str, Provenance] = {
    "plant.motor.resistance_ohm": _P(
        unit="Ω", source="DOMAIN §4.1 (≈3.4 Ω recalled, 3–4 Ω)", confidence="U"
    ),
    "plant.motor.inductance_h": _P(
        unit="H", source="DOMAIN §4.1, sister SR motors 70–110 µH", confidence="U"
    ),
    "plant.motor.torque_constant_nm_per_a": _P(
        unit="N·m/A", source="DOMAIN §4.1: k_M = k_E in SI", confidence="I"
    ),
    "plant.motor.back_emf_v_s_per_rad": _P(
        unit="V·s/rad", source="DOMAIN §4.1: ≈ U_N/n₀ = 6 V / 900.6 rad/s", confidence="I"
    ),
    "plant.motor.rotor_inertia_kg_m2": _P(
        unit="kg·m²", source="DOMAIN §4.1: 0.8–1.2 g·cm²", confidence="U"
    ),
    "plant.motor.quasi_static_current": _P(
        unit="-",
        source="modelling choice: the electrical pole L/R ≈ 21 µs is integrated",
        confidence="I",
    ),
    "plant.motor_friction.static_torque_nm": _P(
        unit="N·m", source="assumed 1.2 × Coulomb torque (no datasheet value)", confidence="U"
    ),
    "plant.motor_friction.coulomb_torque_nm": _P(
        unit="N·m", source="DOMAIN §4.1: friction torque MR ≈ 0.1 mN·m", confidence="U"
    ),
    "plant.motor_friction.viscous_nm_s_per_rad": _P(
        unit="N·m·s/rad", source="DOMAIN §3.1: (k_M·I₀ − MR)/ω₀ with I₀ ≈ 0.018 A", confidence="U"
    ),
    "plant.motor_friction.stribeck_velocity_rad_per_s": _P(
        unit="rad/s", source="assumed (≈ 0.1 mm/s at the table)", confidence="U"
    ),
    "plant.motor_friction.stribeck_exponent": _P(
        unit="-", source="DOMAIN §3.1: δ = 2 common", confidence="K"
    ),
    "plant.gearhead.ratio": _P(unit="-", source="seed paper: 19:1", confidence="B"),
    "plant.gearhead.efficiency": _P(
        unit="-", source="DOMAIN §4.2: 2-stage planetary ≈ 0.8", confidence="U"
    ),
    "plant.screw.lead_m": _P(unit="m", source="seed paper: lead 2 mm", confidence="B"),
    "plant.screw.efficiency": _P(unit="-", source="DOMAIN §4.4: practical ≈ 0.9", confidence="U"),
    "plant.screw.inertia_kg_m2": _P(
        unit="kg·m²", source="Ø6 × 100 mm steel shaft: m r²/2 ≈ 1e-7", confidence="I"
    ),
    "plant.table.mass_kg": _P(
        unit="kg", source="DOMAIN §4.3: table/carriage ≲ 1 kg", confidence="U"
    ),
    "plant.table.external_force_n": _P(
        unit="N", source="horizontal axis, no cable force modelled", confidence="U"
    ),
    "plant.dahl.coulomb_force_n": _P(
        unit="N",
        source="seed paper: Fc = 30.4 N (motor current at constant velocity)",
        confidence="B",
    ),
    "plant.dahl.stiffness_n_per_m": _P(
        unit="N/m",
        source="seed paper prints σ = 75 'N/m'; only 75 N/µm is plausible (presliding Fc/σ ≈ 0.4 µm), DOMAIN §3.2",
        confidence="I",
    ),
    "plant.dahl.exponent": _P(unit="-", source="seed paper: n = 1", confidence="B"),
    "encoder.count_m": _P(
        unit="m", source="seed paper: Heidenhain encoder, 100 nm resolution", confidence="B"
    ),
    "encoder.side": _P(
        unit="-", source="seed paper: the linear encoder reads the table", confidence="B"
    ),
    "output_stage.amplifier_gain": _P(
        unit="V/V", source="assumed unity-gain linear amplifier", confidence="U"
    ),
    "output_stage.amplifier_limit_v": _P(
        unit="V", source="seed paper: motor nominal voltage 6 V", confidence="B"
    ),
    "controller.kp": _P(unit="output units/count", source="seed paper Table 1", confidence="B"),
    "controller.ki": _P(
        unit="output units/(count·sample)", source="seed paper Table 1", confidence="B"
    ),
    "controller.kd": _P(
        unit="output units/count",
        source="seed paper Table 1 (damping sign, DOMAIN §2.3)",
        confidence="B",
    ),
    "controller.output_unit_v": _P(
        unit="V",
        source="chosen: 0.1 mV per unit (≡ e in µm, u in mV); with 1 mV or 1 DAC LSB the Table 1 gains limit-cycle (DOMAIN §2.3; checked with this model, see README, Conventions)",
        confidence="I",
    ),
    "controller.dac_lsb_v": _P(
        unit="V", source="16-bit ±10 V analog output: 20 V / 65536 (NI 9263)", confidence="K"
    ),
    "controller.output_min": _P(
        unit="output units", source="−6 V / 0.1 mV: the amplifier limit", confidence="I"
    ),
    "controller.output_max": _P(
        unit="output units", source="+6 V / 0.1 mV: the amplifier limit", confidence="I"
    ),
    "controller.anti_windup": _P(
        unit="-",
        source="conditional integration: without anti-windup the 10 mm step overshoots by mm (DOMAIN §2.3)",
        confidence="U",
    ),
    "controller.clock_hz": _P(
        unit="Hz", source="NI FPGA default 40 MHz top-level clock (DOMAIN §2.5)", confidence="K"
    ),
    "controller.ticks_per_sample": _P(
        unit="ticks", source="T = 1 ms (seed paper) at 40 MHz", confidence="B"
    ),
    "controller.latency_ticks": _P(
        unit="ticks",
        source="schedule: latch 1 + error 1 + multiply 2 + integrate 1 + sum/saturate 2 + DAC scale 2 + AO write 1 = 10 ticks, plus ≈3 µs AO conversion (120 ticks)",
        confidence="U",
    ),
    "controller.formats": _P(
        unit="-",
        source="custom FPGA PID (Kp = 450 does not fit NI's Q8.8 gains, DOMAIN §2.3): gains ⟨s,24,16⟩, counter ⟨s,32,32⟩ wrap, error ⟨s,32,32⟩, terms and integrator ⟨s,48,40⟩, output ⟨s,32,24⟩, DAC ⟨s,16,16⟩, all saturating, round half even",
        confidence="U",
    ),
}


def _fxp(d: dict[str, Any]) -> Fxp:
    return Fxp(**d)


def table1_gains(step_m: float) -> tuple[float, float, float]:
    """The paper's hand-tuned (Kp, Ki, Kd) for a step size (nearest Table 1 row, log scale).

    Parameters
    ----------
    step_m : float
        Step size, m (100 µm, 500 µm, 1 mm and 10 mm are the table's rows).
    """
    if not (math.isfinite(step_m) and step_m != 0.0):
        raise _core.ConfigError(
            f"step_m = {step_m} is invalid: expected a finite non-zero step in m"
        )
    rows: dict[float, tuple[float, float, float]] = _core.seed_values()["table1_gains"]
    best = min(rows, key=lambda s: abs(math.log(s) - math.log(abs(step_m))))
    return rows[best]


def seed_plant() -> Plant:
    """The seed axis plant (values and provenance in :data:`SEED_PROVENANCE`)."""
    v = _core.seed_values()
    return Plant(
        motor=Motor(**v["motor"]),
        motor_friction=StribeckFriction(**v["motor_friction"]),
        gearhead=Gearhead(**v["gearhead"]),
        screw=BallScrew(**v["screw"]),
        table=Table(**v["table"]),
        dahl=DahlFriction(**v["dahl"]),
    )


def seed_controller(step_m: float = 1e-3) -> FpgaPid:
    """The seed FPGA loop with the Table 1 gains for ``step_m``."""
    c = dict(_core.seed_values()["controller"])
    for k in list(c):
        if k.endswith("_format"):
            c[k] = _fxp(c[k])
    kp, ki, kd = table1_gains(step_m)
    return FpgaPid(kp=kp, ki=ki, kd=kd, **c)


def seed(step_m: float = 1e-3) -> System:
    """The whole seed system (plant, FPGA loop with Table 1 gains for ``step_m``, encoder,
    output stage, integrator options).

    Examples
    --------
    >>> import nanostage
    >>> s = nanostage.presets.seed(100e-6)
    >>> s.controller.kp, s.controller.ki, s.controller.kd
    (450.0, 2.0, 40.0)
    """
    v = _core.seed_values()
    return System(
        plant=seed_plant(),
        controller=seed_controller(step_m),
        encoder=Encoder(**v["encoder"]),
        output_stage=OutputStage(**v["output_stage"]),
        integrator=IntegratorOptions(**v["integrator"]),
    )


def with_gains(system: System, *, kp: float, ki: float, kd: float) -> System:
    """A copy of ``system`` (with an FPGA PID) with other PID gains."""
    ctl = system.controller
    if not isinstance(ctl, FpgaPid):
        raise TypeError(f"with_gains needs an FpgaPid controller, not {type(ctl).__name__}")
    return replace(system, controller=replace(ctl, kp=kp, ki=ki, kd=kd))


def table1_system(step_m: float, model: System | None = None) -> System:
    """The system of a Table 1 study at ``step_m``: :func:`seed` ``(step_m)``, or with
    ``model`` that model (plant, effects, controller formats and timing, encoder, output
    stage, integrator) with the Table 1 gains of ``step_m`` in place of its own PID gains.

    Raises
    ------
    ConfigError
        If ``model`` does not have a rigid-axis plant (:class:`Plant`) and an FPGA PID
        (:class:`FpgaPid`): the Table 1 studies are of such an axis.
    """
    if model is None:
        return seed(step_m)
    if not isinstance(model, System):
        raise _core.ConfigError(
            f"model = {model!r} is invalid: expected a nanostage.System (e.g. "
            "nanostage.load_model(path))"
        )
    if not isinstance(model.plant, Plant) or not isinstance(model.controller, FpgaPid):
        raise _core.ConfigError(
            f"model: a {type(model.plant).__name__} plant with a "
            f"{type(model.controller).__name__} controller is not a Table 1 axis: expected "
            'plant kind = "rigid_axis" and controller kind = "fpga_pid" (as in the seed '
            "model)"
        )
    kp, ki, kd = table1_gains(step_m)
    return with_gains(model, kp=kp, ki=ki, kd=kd)


#: EMPS numbers (Janot, Gautier, Brunot 2019; ../shared/data/emps/SOURCE.md): the
#: authors' IDIM-LS identification, symmetric and asymmetric, and the logged controller.
EMPS_VALUES: dict[str, float] = {
    "drive_gain_n_per_v": 35.1507,
    "mass_kg": 95.1089,
    "viscous_n_s_per_m": 203.5034,
    "coulomb_force_n": 20.3935,
    "offset_n": -3.1648,
    "kp_per_s": 160.18,
    "kv_v_s_per_m": 243.45,
    "count_m": 5e-8,
    "saturation_v": 10.0,
    "asym_mass_kg": 95.1540,
    "viscous_pos_n_s_per_m": 166.7061,
    "coulomb_pos_n": 20.1440,
    "viscous_neg_n_s_per_m": 240.4236,
    "coulomb_neg_n": 20.6277,
}


def emps(*, asymmetric: bool = False) -> System:
    """The EMPS axis: a force drive (35.15 N/V) moving a lumped mass with Coulomb + viscous
    friction (true stiction at Fc) and a constant offset force, the dSPACE cascade controller
    in floating point (kp = 160.18 1/s, kv = 243.45 V·s/m, velocity from the two-sample
    filtered difference, ±10 V), a 5e-8 m encoder on the motor, and the one-sample delay of
    the authors' reference model between the controller output and the plant. Values: the
    authors' symmetric identification, or with ``asymmetric`` their direction-dependent one
    (levels and viscous coefficients as mean ± asymmetry; the asymmetric set has no offset).
    """
    v = EMPS_VALUES
    if asymmetric:
        fc = 0.5 * (v["coulomb_pos_n"] + v["coulomb_neg_n"])
        fv = 0.5 * (v["viscous_pos_n_s_per_m"] + v["viscous_neg_n_s_per_m"])
        friction = StaticFrictionMap(
            static_force_n=fc,
            coulomb_force_n=fc,
            viscous_n_s_per_m=fv,
            asymmetry=(v["coulomb_pos_n"] - fc) / fc,
            viscous_asymmetry=(v["viscous_pos_n_s_per_m"] - fv) / fv,
        )
        mass, offset = v["asym_mass_kg"], 0.0
    else:
        friction = StaticFrictionMap(
            static_force_n=v["coulomb_force_n"],
            coulomb_force_n=v["coulomb_force_n"],
            viscous_n_s_per_m=v["viscous_n_s_per_m"],
        )
        mass, offset = v["mass_kg"], v["offset_n"]
    return System(
        plant=ForceDrivePlant(
            drive_gain_n_per_v=v["drive_gain_n_per_v"],
            mass_kg=mass,
            friction=friction,
            external_force_n=offset,
        ),
        controller=CascadeController(
            kp_per_s=v["kp_per_s"],
            kv_v_s_per_m=v["kv_v_s_per_m"],
            sample_period_s=1e-3,
            saturation_v=v["saturation_v"],
        ),
        encoder=Encoder(count_m=v["count_m"], side="motor"),
        effects=Effects(computation_delay_samples=1),
    )


def emps_naive() -> System:
    """A deliberately naive EMPS model: mass and viscous friction only (no Coulomb friction,
    no offset), for the diagnosis to start from."""
    s = emps()
    p = s.plant
    assert isinstance(p, ForceDrivePlant)
    friction = replace(p.friction, static_force_n=0.0, coulomb_force_n=0.0)
    return replace(s, plant=replace(p, friction=friction, external_force_n=0.0))


#: Presets by name (the diagnosis manifest's ``[model] preset``).
PRESETS: dict[str, Callable[[], System]] = {
    "seed": seed,
    "emps": emps,
    "emps_naive": emps_naive,
    "emps_asymmetric": lambda: emps(asymmetric=True),
}

#: The controller kind of each preset (used when a diagnosis manifest gives none).
PRESET_CONTROLLER_KIND: Final[Mapping[str, str]] = MappingProxyType(
    {"seed": "fpga_pid", "emps": "cascade"}
)

#: Travel of each preset's axis, m: SEED.md's 50 mm for the seed axis; 0.5 m for the EMPS
#: (the data set spans 0.25 m). A manifest may give its own (``model.travel_m``).
PRESET_TRAVEL_M: Final[Mapping[str, float]] = MappingProxyType(
    {"seed": 0.05, "emps": 0.5, "emps_naive": 0.5, "emps_asymmetric": 0.5}
)


def preset_names() -> tuple[str, ...]:
    """Names of the presets (what a manifest's ``model.preset`` may take), from :data:`PRESETS`."""
    return tuple(str(k) for k in PRESETS)


def preset_system(name: str) -> System:
    """The :class:`nanostage.System` of the preset ``name``.

    Raises
    ------
    KeyError
        If there is no such preset.
    """
    return PRESETS[name]()
