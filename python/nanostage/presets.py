"""Presets: the seed axis of the paper (with its Table 1 gains and each value's unit, source
and confidence) and the EMPS axis.

Each preset's numbers are written once, in a model file shipped with the package
(``nanostage/model_files/seed.model.toml``, ``emps.model.toml``), read here with the model
file loader (:func:`nanostage.model_file.parse_model`, parsed once per process) and by the
Rust tests and benches. Confidence tags follow DOMAIN.md: ``B`` stated in the seed paper,
``I`` derived here (arithmetic shown), ``U`` uncertain planning value, ``K`` textbook.
"""

from __future__ import annotations

import copy
import functools
import importlib.resources
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from types import MappingProxyType
from typing import Any, Final

from . import _core
from .config import ForceDrivePlant, FpgaPid, Plant, System, did_you_mean
from .effects import StaticFrictionMap
from .model_file import ModelDocument, ModelFileError, parse_model

__all__ = [
    "PRESETS",
    "PRESET_CONTROLLER_KIND",
    "PRESET_TRAVEL_M",
    "SEED_PROVENANCE",
    "Provenance",
    "check_preset_name",
    "preset_names",
    "preset_provenance",
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


_PACKAGE_DIR: Final = "model_files"
#: The shipped model files (``model_files/<name>.model.toml``) the presets are read from.
_SEED_FILE: Final = "seed"
_EMPS_FILE: Final = "emps"


def _file_label(name: str) -> str:
    """The shipped model file ``name`` as the package path that names it in messages and
    provenance (``nanostage/model_files/<name>.model.toml``)."""
    return f"nanostage/{_PACKAGE_DIR}/{name}.model.toml"


@functools.cache
def _document(name: str) -> ModelDocument:
    """The shipped model file ``model_files/<name>.model.toml`` read whole (parsed once)."""
    resource = importlib.resources.files(__package__).joinpath(_PACKAGE_DIR, f"{name}.model.toml")
    text = resource.read_text(encoding="utf-8")
    return parse_model(text, source=_file_label(name))


def _file_error(name: str, message: str) -> ModelFileError:
    return ModelFileError(f"{_file_label(name)}: {message}")


def _number(name: str, key: str, raw: Any) -> float:
    if not isinstance(raw, int | float) or isinstance(raw, bool) or not math.isfinite(raw):
        raise _file_error(name, f"{key} = {raw!r} is invalid: expected a finite number")
    return float(raw)


@functools.cache
def _table1_rows() -> dict[float, tuple[float, float, float]]:
    """Table 1 of the seed paper from the seed file: step size, m -> (Kp, Ki, Kd)."""
    raw = _document(_SEED_FILE).provenance.get("table1_gains")
    if not isinstance(raw, list) or not raw:
        raise _file_error(
            _SEED_FILE, "provenance.table1_gains is missing: expected an array of tables"
        )
    rows: dict[float, tuple[float, float, float]] = {}
    for i, row in enumerate(raw):
        key = f"provenance.table1_gains[{i}]"
        if not isinstance(row, dict) or sorted(row) != ["kd", "ki", "kp", "step_m"]:
            raise _file_error(
                _SEED_FILE, f"{key} is invalid: expected a table of step_m, kp, ki, kd"
            )
        step = _number(_SEED_FILE, f"{key}.step_m", row["step_m"])
        if not step > 0.0:
            raise _file_error(_SEED_FILE, f"{key}.step_m = {step!r} is invalid: expected > 0 m")
        kp, ki, kd = (_number(_SEED_FILE, f"{key}.{k}", row[k]) for k in ("kp", "ki", "kd"))
        rows[step] = (kp, ki, kd)
    return rows


@functools.cache
def _seed_system() -> System:
    """The seed file's system (its controller has the 1 mm row of Table 1)."""
    system = _document(_SEED_FILE).system
    ctl = system.controller
    assert isinstance(ctl, FpgaPid)
    if (ctl.kp, ctl.ki, ctl.kd) != table1_gains(1e-3):
        raise _file_error(
            _SEED_FILE,
            f"controller gains (kp, ki, kd) = {(ctl.kp, ctl.ki, ctl.kd)} are not the 1 mm row "
            f"of provenance.table1_gains {table1_gains(1e-3)}",
        )
    return system


def _seed_provenance() -> dict[str, Provenance]:
    raw = _document(_SEED_FILE).provenance.get("values", {})
    out: dict[str, Provenance] = {}
    for path, entry in raw.items():
        if (
            not isinstance(entry, dict)
            or sorted(entry) != ["confidence", "source", "unit"]
            or not all(isinstance(v, str) for v in entry.values())
        ):
            raise _file_error(
                _SEED_FILE,
                f'provenance.values."{path}" is invalid: expected a table of the strings '
                "unit, source, confidence",
            )
        out[path] = Provenance(**entry)
    return out


#: Unit, source and confidence of every seed value, keyed by dotted field path (the seed
#: file's ``[provenance.values]``).
SEED_PROVENANCE: dict[str, Provenance] = _seed_provenance()


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
    rows = _table1_rows()
    best = min(rows, key=lambda s: abs(math.log(s) - math.log(abs(step_m))))
    return rows[best]


def seed_plant() -> Plant:
    """The seed axis plant (values and provenance in :data:`SEED_PROVENANCE`)."""
    plant = _seed_system().plant
    assert isinstance(plant, Plant)
    return plant


def seed_controller(step_m: float = 1e-3) -> FpgaPid:
    """The seed FPGA loop with the Table 1 gains for ``step_m``."""
    controller = _seed_system().controller
    assert isinstance(controller, FpgaPid)
    kp, ki, kd = table1_gains(step_m)
    return replace(controller, kp=kp, ki=ki, kd=kd)


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
    kp, ki, kd = table1_gains(step_m)
    return with_gains(_seed_system(), kp=kp, ki=ki, kd=kd)


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


def emps(*, asymmetric: bool = False) -> System:
    """The EMPS axis: a force drive (35.15 N/V) moving a lumped mass with Coulomb + viscous
    friction (true stiction at Fc) and a constant offset force, the dSPACE cascade controller
    in floating point (kp = 160.18 1/s, kv = 243.45 V·s/m, velocity from the two-sample
    filtered difference, ±10 V), a 5e-8 m encoder on the motor, and the one-sample delay of
    the authors' reference model between the controller output and the plant. Values: the
    authors' symmetric identification, or with ``asymmetric`` their direction-dependent one
    (levels and viscous coefficients as mean ± asymmetry; the asymmetric set has no offset).
    """
    system = _document(_EMPS_FILE).system
    if not asymmetric:
        return system
    plant = system.plant
    assert isinstance(plant, ForceDrivePlant)
    raw = _document(_EMPS_FILE).provenance.get("asymmetric")
    keys = [
        "coulomb_neg_n",
        "coulomb_pos_n",
        "mass_kg",
        "viscous_neg_n_s_per_m",
        "viscous_pos_n_s_per_m",
    ]
    if not isinstance(raw, dict) or sorted(raw) != keys:
        raise _file_error(
            _EMPS_FILE,
            f"provenance.asymmetric is invalid: expected a table of {', '.join(keys)}",
        )
    v = {k: _number(_EMPS_FILE, f"provenance.asymmetric.{k}", raw[k]) for k in keys}
    fc = 0.5 * (v["coulomb_pos_n"] + v["coulomb_neg_n"])
    fv = 0.5 * (v["viscous_pos_n_s_per_m"] + v["viscous_neg_n_s_per_m"])
    friction = StaticFrictionMap(
        static_force_n=fc,
        coulomb_force_n=fc,
        viscous_n_s_per_m=fv,
        asymmetry=(v["coulomb_pos_n"] - fc) / fc,
        viscous_asymmetry=(v["viscous_pos_n_s_per_m"] - fv) / fv,
    )
    return replace(
        system,
        plant=replace(plant, mass_kg=v["mass_kg"], friction=friction, external_force_n=0.0),
    )


def emps_naive() -> System:
    """A deliberately naive EMPS model: mass and viscous friction only (no Coulomb friction,
    no offset), for the diagnosis to start from."""
    s = emps()
    p = s.plant
    assert isinstance(p, ForceDrivePlant)
    friction = replace(p.friction, static_force_n=0.0, coulomb_force_n=0.0)
    return replace(s, plant=replace(p, friction=friction, external_force_n=0.0))


@dataclass(frozen=True, slots=True)
class _Preset:
    """A preset: how it is built, the shipped model file it is read from
    (``model_files/<file>.model.toml``) and what it is of that file."""

    build: Callable[[], System]
    file: str
    note: str


#: Every preset by name: the one place that says which shipped file each preset is read
#: from (:data:`PRESETS` and :func:`preset_provenance` are read from it).
_PRESET_SOURCES: Final[Mapping[str, _Preset]] = MappingProxyType(
    {
        "seed": _Preset(seed, _SEED_FILE, "the file's model (the 1 mm Table 1 gains)"),
        "emps": _Preset(emps, _EMPS_FILE, "the file's model"),
        "emps_naive": _Preset(
            emps_naive,
            _EMPS_FILE,
            "the file's model without Coulomb friction and offset force (mass and viscous "
            "friction only)",
        ),
        "emps_asymmetric": _Preset(
            lambda: emps(asymmetric=True),
            _EMPS_FILE,
            "the file's model with provenance.asymmetric (the authors' direction-dependent "
            "identification) in place of the symmetric one, no offset force",
        ),
    }
)

#: Presets by name (the diagnosis manifest's ``[model] preset``).
PRESETS: dict[str, Callable[[], System]] = {
    name: preset.build for name, preset in _PRESET_SOURCES.items()
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


def check_preset_name(name: object, label: str = "preset") -> None:
    """Raise :class:`nanostage.ConfigError` unless ``name`` is a preset's name; the message
    names it as ``label`` (e.g. ``--preset``), the nearest preset and every preset."""
    if isinstance(name, str) and name in _PRESET_SOURCES:
        return
    names = tuple(_PRESET_SOURCES)
    hint = did_you_mean(name, names) if isinstance(name, str) else ""
    raise _core.ConfigError(
        f"{label} {name!r} is unknown{hint}; the presets are: {', '.join(names)}"
    )


def preset_provenance(name: str) -> dict[str, Any]:
    """Where the preset ``name`` comes from: the ``[provenance]`` table of the shipped model
    file it is read from, whole (its ``source``, and for the seed Table 1's gains
    ``table1_gains`` and each value's unit, source and confidence ``values``, for the EMPS
    the authors' direction-dependent identification ``asymmetric``), with ``preset_file``,
    that file's package path (``nanostage/model_files/<file>.model.toml``), and
    ``preset_note``, what the preset is of that file. ``nanostage model export PRESET``
    writes it as the model file's provenance (adding ``preset``, ``command`` and
    ``version``).

    The result is a fresh copy: changing it changes no preset.

    Raises
    ------
    ConfigError
        If there is no such preset (the message names it, the nearest preset and every
        preset).

    Examples
    --------
    >>> import nanostage
    >>> prov = nanostage.presets.preset_provenance("emps_naive")
    >>> prov["preset_file"]
    'nanostage/model_files/emps.model.toml'
    """
    check_preset_name(name)
    preset = _PRESET_SOURCES[name]
    return {
        **copy.deepcopy(dict(_document(preset.file).provenance)),
        "preset_file": _file_label(preset.file),
        "preset_note": preset.note,
    }
