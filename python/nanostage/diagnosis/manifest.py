"""The diagnosis manifest: which model, which free parameters, which measured experiments.

A manifest is a TOML file. Everything in it is checked when it is loaded
(:func:`load_manifest`), and :meth:`Manifest.experiments` reads and checks every trace, so
all input errors surface before any fitting starts. Errors are :class:`ManifestError`
(a :class:`ValueError`) naming the manifest file and the key (and the line for TOML
syntax errors).

Schema
------
.. code-block:: toml

    [model]
    preset = "seed"                 # a preset name (see PRESET_NAMES()), or a model file:
    # file = "axis.model.toml"      #   a model file (schema_version = 1, docs/model-file.md)
                                    #   is the nominal model in place of a preset
    travel_m = 0.05                 # optional: the axis travel, m (default: the preset's,
                                    #   PRESET_TRAVEL_M); position columns beyond it are
                                    #   taken for millimetres
    file = "model.toml"             # optional with a preset: a TOML file of overrides,
                                    #   relative to the manifest, e.g. [plant.table]
                                    #   mass_kg = 0.8 (a file with schema_version is a
                                    #   model file instead, and then preset is not given)
    free = ["plant.dahl.coulomb_force_n", "plant.dahl.stiffness_n_per_m"]
                                    # optional: free parameters, dotted paths into the
                                    #   preset's dataclass tree (numeric fields only)

    [model.overrides]               # optional: dotted path -> value; applied after `file`
    "plant.table.mass_kg" = 0.8     #   (bare dotted keys  plant.table.mass_kg = 0.8  work too)

    [model.bounds]                  # optional, per free parameter: [lower, upper]; must
    "plant.dahl.coulomb_force_n" = [5.0, 100.0]   # contain the (overridden) preset value.
                                    # Default: [value/3, value*3] (sorted for value < 0;
                                    # a value of 0 needs explicit bounds)

    [controller]                    # optional: the default controller of all experiments
    kind = "fpga_pid"               # "fpga_pid" (gains kp, ki, kd: the Table 1 integer gains)
                                    #   or "cascade" (gains kp_per_s, kv_v_s_per_m);
                                    #   default: the preset's kind (seed: fpga_pid)
    kp = 450.0                      # gains not given are the preset's

    [diagnosis]                     # optional
    candidates = "all"              # "all" or a list of effect names (EFFECT_NAMES)
    seed = 1                        # integer random seed (default 0)

    [[experiment]]                  # one or more
    name = "step_100um_1"           # required, unique
    file = "traces/step_100um_1.csv"  # required, relative to the manifest (CSV, .npz, .mat,
                                    #   .tdms); must resolve inside the manifest's folder
    role = "train"                  # optional: "train" | "validate"; all experiments or none.
                                    #   None: leave-one-experiment-out folds
    columns = { position_m = "qm" } # optional column map {standard name: name in the file}
                                    #   (.tdms: "Group/Channel", or a channel name)
    group = "Measurements"          # optional, .tdms only: the group of bare channel names
    units = "mm"                    # optional: unit of the length columns in the file, or
                                    #   { position_m = "um", time_s = "ms" } per column
    window_s = [0.0, 12.0]          # optional time window [start, stop) in s
    controller = { kp = 12.0 }      # optional per-experiment controller: merged over the
                                    #   default (a different `kind` replaces it)

Unknown keys anywhere are errors (with a "did you mean" hint), so typos do not pass
silently.

Files the manifest names (``model.file``, every ``experiment.file``) must resolve, after
symbolic links, inside the manifest's folder, unless the caller names another root
(``trace_root=``, CLI ``--trace-root``). The traces are read within size limits
(:class:`~nanostage.diagnosis.traces.TraceLimits`, ``limits=``): per trace, and all the
experiments together.

``nanostage predict`` reads the same schema (:func:`load_prediction_manifest`) without the
diagnosis keys (``model.free``, ``model.bounds``, ``[diagnosis]``, ``experiment.role``, an
error there), with experiment names that become file names
(:func:`nanostage.output.check_file_stems`) and the trace columns of
:func:`~nanostage.diagnosis.traces.read_prediction_trace`.
"""

from __future__ import annotations

import dataclasses
import math
import re
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any, Final, Literal

from .._core import ConfigError
from ..config import Plant, System, did_you_mean, field_paths, get_path, replace_paths
from ..effects import EFFECT_NAMES
from ..experiment import Experiment
from ..model_file import load_model
from ..output import OutputError, check_file_stems
from ..presets import PRESET_CONTROLLER_KIND, PRESET_TRAVEL_M, preset_names, preset_system
from .scatter import MAX_LEVEL_SCATTER
from .settings import DEFAULT_LEVEL_SCATTER
from .traces import (
    ALL_COLUMNS,
    LENGTH_UNITS,
    MAX_TRAVEL_M,
    POSITION_COLUMNS,
    PREDICTION_COLUMNS,
    TIME_UNITS,
    TraceError,
    TraceLimits,
    cut_window,
    escaped,
    read_trace,
)

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

__all__ = [
    "CONTROLLER_GAINS",
    "ROLES",
    "ControllerSpec",
    "DiagnosisSpec",
    "ExperimentSpec",
    "Fold",
    "Manifest",
    "ManifestError",
    "ModelSpec",
    "check_total_samples",
    "load_manifest",
    "load_prediction_manifest",
]

Role = Literal["train", "validate"]
#: Valid experiment roles.
ROLES: Final[tuple[str, ...]] = ("train", "validate")
#: Controller kinds and the gains each takes.
CONTROLLER_GAINS: Final[Mapping[str, tuple[str, ...]]] = MappingProxyType(
    {"fpga_pid": ("kp", "ki", "kd"), "cascade": ("kp_per_s", "kv_v_s_per_m")}
)

_TOP_KEYS: Final = ("model", "controller", "diagnosis", "experiment")
_MODEL_KEYS: Final = ("preset", "file", "free", "overrides", "bounds", "travel_m")
_DIAGNOSIS_KEYS: Final = ("candidates", "seed", "level_scatter")
_EXPERIMENT_KEYS: Final = (
    "name",
    "file",
    "role",
    "columns",
    "group",
    "units",
    "window_s",
    "controller",
)
#: Keys only the diagnosis reads (an error in a prediction manifest), by table.
_DIAGNOSE_ONLY: Final[Mapping[str, tuple[str, ...]]] = MappingProxyType(
    {"": ("diagnosis",), "model": ("free", "bounds"), "experiment": ("role",)}
)
#: Largest ``model.travel_m`` accepted, m.
_MAX_TRAVEL_SETTING_M: Final = 10.0
Purpose = Literal["diagnose", "predict"]


class ManifestError(ValueError):
    """An invalid manifest.

    The message reads ``"<manifest>, line <n>: <reason>"`` for TOML syntax errors and
    ``"<manifest>, key '<key>': <reason>"`` otherwise; keys are written as paths such as
    ``model.free[1]`` or ``experiment[2].window_s``.

    Attributes
    ----------
    file : str
        The manifest (or the model overrides file).
    key : str or None
        The offending key.
    line : int or None
        1-based line of a TOML syntax error.
    reason : str
        The message without the location.
    """

    def __init__(
        self, message: str, *, file: str, key: str | None = None, line: int | None = None
    ) -> None:
        self.reason = message
        self.file = file
        self.key = key
        self.line = line
        parts = [file]
        if line is not None:
            parts.append(f"line {line}")
        if key is not None:
            parts.append(f"key {key!r}")
        super().__init__(f"{', '.join(parts)}: {message}")


# --------------------------------------------------------------------------------------------
# Parsed manifest
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class ControllerSpec:
    """A controller: its kind and the gains the manifest sets (others are the preset's)."""

    kind: str
    gains: Mapping[str, float]


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class ModelSpec:
    """The model: preset, overrides, free parameters with bounds and start values.

    Attributes
    ----------
    preset : str or None
        Preset name (None: the nominal model is :attr:`base`).
    file : Path or None
        The overrides file or the model file, resolved.
    overrides : mapping of str to Any
        Dotted path → value (the file's, then the manifest's ``[model.overrides]``).
    free : tuple of str
        Free parameters (dotted paths), in manifest order.
    bounds : mapping of str to (float, float)
        ``(lower, upper)`` of every free parameter (defaults filled in).
    initial : mapping of str to float
        Value of every free parameter in the preset with the overrides applied.
    travel_m : float
        The axis travel, m (``model.travel_m`` or :data:`PRESET_TRAVEL_M`): the scale the
        traces' length columns are checked against.
    base : System or None
        The nominal model of a model file (``model.file`` with ``schema_version``, or the
        ``model=`` argument of :func:`load_manifest`), the overrides not applied; None: the
        preset.
    """

    preset: str | None
    file: Path | None
    overrides: Mapping[str, Any]
    free: tuple[str, ...]
    bounds: Mapping[str, tuple[float, float]]
    initial: Mapping[str, float]
    travel_m: float = MAX_TRAVEL_M
    base: System | None = None

    def nominal(self) -> System:
        """The nominal model before the overrides: the model file's, or the preset's."""
        if self.base is not None:
            return self.base
        assert self.preset is not None
        return preset_system(self.preset)


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class ExperimentSpec:
    """One ``[[experiment]]`` entry, with its file resolved and its controller merged."""

    name: str
    file: Path
    role: Role | None
    columns: Mapping[str, str] | None
    window_s: tuple[float, float] | None
    controller: ControllerSpec
    #: Position of the entry in the manifest (0-based), for error messages.
    index: int = 0
    #: Units of the file's columns (a length unit, or standard name → unit), or None: SI.
    units: str | Mapping[str, str] | None = None
    #: ``.tdms`` files: the group whose channels are read under bare names, or None.
    group: str | None = None


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class DiagnosisSpec:
    """The ``[diagnosis]`` table: candidate effects (resolved), the random seed and the
    run-to-run friction level scatter (relative, 1σ; default 1 %, 0: left out;
    :attr:`~nanostage.diagnosis.settings.DiagnosisSettings.level_scatter`)."""

    candidates: tuple[str, ...]
    seed: int
    level_scatter: float = DEFAULT_LEVEL_SCATTER


@dataclass(frozen=True, slots=True, kw_only=True)
class Fold:
    """One train/validate split of the experiments (by name)."""

    name: str
    train: tuple[str, ...]
    validate: tuple[str, ...]


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class Manifest:
    """A loaded, validated manifest (see the module docstring for the schema).

    Attributes
    ----------
    path : Path
        The manifest file.
    model : ModelSpec
    controller : ControllerSpec
        The default controller.
    diagnosis : DiagnosisSpec
    experiment_specs : tuple of ExperimentSpec
        The ``[[experiment]]`` entries in manifest order.
    limits : TraceLimits
        Size limits of the traces (:meth:`experiments`).
    purpose : {"diagnose", "predict"}
        The command whose schema the manifest was checked against.
    """

    path: Path
    model: ModelSpec
    controller: ControllerSpec
    diagnosis: DiagnosisSpec
    experiment_specs: tuple[ExperimentSpec, ...]
    limits: TraceLimits = field(default_factory=TraceLimits)
    purpose: Purpose = "diagnose"

    def system(self, experiment: ExperimentSpec | None = None) -> Any:
        """The preset with the model overrides and the controller gains applied.

        The gains are those of ``experiment`` (default: the manifest's default controller),
        set as ``controller.<gain>``; gains the manifest does not give keep the preset's
        values. The controller kind was checked against the preset's controller at load.
        """
        system = replace_paths(self.model.nominal(), self.model.overrides)
        ctrl = self.controller if experiment is None else experiment.controller
        gains = {f"controller.{k}": v for k, v in ctrl.gains.items()}
        return replace_paths(system, gains) if gains else system

    def experiments(self) -> list[tuple[ExperimentSpec, Experiment]]:
        """Read and check every experiment's trace (each file once).

        The traces are read in the units the experiments declare, checked against the
        model's travel and within :attr:`limits`: each file, and the samples of all the
        experiments together (counted as they are read, so at most one trace beyond
        ``max_samples_total`` is ever held).

        Raises
        ------
        ManifestError
            Wrapping the :class:`~nanostage.diagnosis.traces.TraceError` (available as
            ``__cause__``), with the experiment's key and name; or naming the total limit.
        """
        cache: dict[tuple[Path, str, str], Experiment] = {}
        out: list[tuple[ExperimentSpec, Experiment]] = []
        total = 0
        for spec in self.experiment_specs:
            key = (
                spec.file,
                repr((sorted((spec.columns or {}).items()), spec.group)),
                _units_key(spec.units),
            )
            try:
                whole = cache.get(key)
                if whole is None:
                    whole = read_trace(
                        spec.file,
                        columns=spec.columns,
                        name=spec.name,
                        units=spec.units,
                        travel_m=self.model.travel_m,
                        limits=self.limits,
                        group=spec.group,
                    )
                    cache[key] = whole
                exp = whole if spec.window_s is None else cut_window(whole, spec.window_s)
            except TraceError as exc:
                raise ManifestError(
                    f"experiment {spec.name!r}: {exc}",
                    file=str(self.path),
                    key=f"experiment[{spec.index}]",
                ) from exc
            total += exp.n_samples
            check_total_samples(total, self.limits, spec, self.path)
            out.append((spec, dataclasses.replace(exp, name=spec.name)))
        return out

    def splits(self) -> list[Fold]:
        """Train/validate folds: one fold from explicit roles, else leave-one-out folds.

        With a single experiment and no roles, the one fold trains on it and validates on
        nothing.
        """
        names = [s.name for s in self.experiment_specs]
        if any(s.role is not None for s in self.experiment_specs):
            return [
                Fold(
                    name="roles",
                    train=tuple(s.name for s in self.experiment_specs if s.role == "train"),
                    validate=tuple(s.name for s in self.experiment_specs if s.role == "validate"),
                )
            ]
        if len(names) == 1:
            return [Fold(name="all", train=(names[0],), validate=())]
        return [
            Fold(
                name=f"leave out {n}",
                train=tuple(m for m in names if m != n),
                validate=(n,),
            )
            for n in names
        ]


# --------------------------------------------------------------------------------------------
# Loading
# --------------------------------------------------------------------------------------------

_LINE_RE = re.compile(r"line (\d+)")
#: Largest manifest (or model overrides) file, bytes: a manifest is a few kB.
MAX_MANIFEST_BYTES: Final[int] = 16 * 2**20


def _load_toml(path: Path, display: str | None = None) -> dict[str, Any]:
    file = display or str(path)
    if not path.is_file():
        raise ManifestError(
            "no such file" if not path.exists() else "not a regular file", file=file
        )
    try:
        size = path.stat().st_size
        if size > MAX_MANIFEST_BYTES:
            raise ManifestError(
                f"{size} bytes is not a manifest (at most {MAX_MANIFEST_BYTES} bytes)", file=file
            )
        with path.open("rb") as fh:
            return tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        m = _LINE_RE.search(str(exc))
        raise ManifestError(
            f"TOML syntax error: {exc}", file=file, line=int(m.group(1)) if m else None
        ) from None
    except UnicodeDecodeError as exc:
        line = bytes(exc.object[: exc.start]).count(b"\n") + 1
        raise ManifestError(
            f"not UTF-8 text: the byte at offset {exc.start} cannot be decoded; save the "
            "file as UTF-8",
            file=file,
            line=line,
        ) from None
    except OSError as exc:
        raise ManifestError(f"cannot read the file ({exc.strerror or exc})", file=file) from None


class _Ctx:
    """Error factory bound to a file, and the rules of the command the manifest is for."""

    def __init__(self, file: Path, purpose: Purpose = "diagnose", root: Path | None = None) -> None:
        self.file = str(file)
        self.purpose: Purpose = purpose
        #: The folder files named in the manifest must resolve inside (None: no check).
        self.root = root

    def err(self, key: str | None, message: str) -> ManifestError:
        return ManifestError(message, file=self.file, key=key)

    def table(self, value: Any, key: str) -> dict[str, Any]:
        if not isinstance(value, dict):
            raise self.err(key, f"expected a table, got {_tname(value)}")
        return value

    def allowed(self, keys: Sequence[str], kind: str) -> tuple[str, ...]:
        """``keys`` of a table (``kind``: "", "model", "experiment") for this purpose."""
        if self.purpose == "diagnose":
            return tuple(keys)
        return tuple(k for k in keys if k not in _DIAGNOSE_ONLY.get(kind, ()))

    def keys(self, table: Mapping[str, Any], allowed: Sequence[str], key: str) -> None:
        kind = re.sub(r"\[\d+\]$", "", key)
        for k in table:
            if k not in allowed:
                where = f"{key}.{k}" if key else k
                if self.purpose == "predict" and k in _DIAGNOSE_ONLY.get(kind, ()):
                    raise self.err(
                        where,
                        "a diagnosis key: nanostage predict does not use it; remove it "
                        f"(valid keys: {', '.join(allowed)})",
                    )
                raise self.err(
                    where,
                    f"unknown key{did_you_mean(k, allowed)}; valid keys: {', '.join(allowed)}",
                )

    def inside(self, key: str, rel: str, base_dir: Path, what: str) -> Path:
        """The file ``rel`` (relative to ``base_dir``) resolved, checked to lie inside
        :attr:`root` after symbolic links."""
        try:
            file = (base_dir / rel).resolve()
        except (OSError, ValueError, RuntimeError) as exc:
            raise self.err(key, f"{what} {escaped(rel)} is not a usable path ({exc})") from None
        if self.root is not None and not file.is_relative_to(self.root):
            where = "the manifest's folder" if self.root == base_dir else "the trace root"
            raise self.err(
                key,
                f"{what} {escaped(rel)} resolves to {str(file)!r}, outside {where} "
                f"{str(self.root)!r}; move it inside, or allow another folder with "
                "trace_root= (CLI --trace-root DIR)",
            )
        return file

    def string(self, value: Any, key: str) -> str:
        if not isinstance(value, str) or not value:
            raise self.err(key, f"expected a non-empty string, got {_tname(value)}")
        return value

    def number(self, value: Any, key: str) -> float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise self.err(key, f"expected a number, got {_tname(value)}")
        v = float(value)
        if not math.isfinite(v):
            raise self.err(key, f"expected a finite number, got {v!r}")
        return v


def _tname(value: Any) -> str:
    if isinstance(value, dict):
        return "a table"
    if isinstance(value, list):
        return "an array"
    return f"{type(value).__name__} {value!r}"


def _flatten(table: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested TOML tables → dotted paths (quoted ``"a.b"`` keys and bare ``a.b`` keys alike)."""
    out: dict[str, Any] = {}
    for k, v in table.items():
        p = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flatten(v, p + "."))
        else:
            out[p] = v
    return out


def _check_override(ctx: _Ctx, root: Any, path: str, value: Any, key: str) -> Any:
    try:
        current = get_path(root, path)
    except KeyError as exc:
        raise ctx.err(key, str(exc.args[0])) from None
    if dataclasses.is_dataclass(current):
        raise ctx.err(key, f"{path!r} is a group of fields; set its fields one by one")
    if isinstance(current, bool):
        if not isinstance(value, bool):
            raise ctx.err(key, f"expected true or false, got {_tname(value)}")
        return value
    if isinstance(current, int | float):
        v = ctx.number(value, key)
        if isinstance(current, int):
            if v != math.floor(v):
                raise ctx.err(key, f"expected an integer, got {value!r}")
            return int(v)
        return v
    if isinstance(current, str):
        return ctx.string(value, key)
    raise ctx.err(key, f"cannot override a field of type {type(current).__name__}")


def _parse_controller(
    ctx: _Ctx,
    raw: Any,
    key: str,
    base: ControllerSpec | None,
    default_kind: str,
    system: Any,
) -> ControllerSpec:
    table = ctx.table(raw, key)
    kind_raw = table.get("kind", base.kind if base is not None else default_kind)
    kind = ctx.string(kind_raw, f"{key}.kind")
    if kind not in CONTROLLER_GAINS:
        raise ctx.err(
            f"{key}.kind",
            f"unknown controller kind {kind!r}{did_you_mean(kind, list(CONTROLLER_GAINS))}; valid "
            f"kinds: {', '.join(CONTROLLER_GAINS)}",
        )
    controller = getattr(system, "controller", None)
    if dataclasses.is_dataclass(controller):
        have = {f.name for f in dataclasses.fields(controller)}
        if not set(CONTROLLER_GAINS[kind]) <= have:
            fits = [k for k, g in CONTROLLER_GAINS.items() if set(g) <= have]
            raise ctx.err(
                f"{key}.kind",
                f"controller kind {kind!r} does not fit the preset's controller "
                f"({type(controller).__name__}); use {' or '.join(map(repr, fits)) or 'its kind'}",
            )
    allowed = ("kind", *CONTROLLER_GAINS[kind])
    ctx.keys(table, allowed, key)
    gains: dict[str, float] = {}
    if base is not None and base.kind == kind:
        gains.update(base.gains)
    for g in CONTROLLER_GAINS[kind]:
        if g in table:
            gains[g] = ctx.number(table[g], f"{key}.{g}")
    return ControllerSpec(kind=kind, gains=MappingProxyType(gains))


def _read_model_file(ctx: _Ctx, path: Path) -> System:
    try:
        return load_model(path)
    except (ConfigError, OSError) as exc:
        raise ctx.err("model.file", str(exc)) from None


def _parse_model(
    ctx: _Ctx, raw: Any, base_dir: Path, model: System | None = None
) -> tuple[ModelSpec, Any]:
    table = ctx.table(raw, "model")
    ctx.keys(table, ctx.allowed(_MODEL_KEYS, "model"), "model")
    model_file: Path | None = None
    file_data: dict[str, Any] | None = None
    if "file" in table:
        model_file = ctx.inside(
            "model.file", ctx.string(table["file"], "model.file"), base_dir, "model file"
        )
        if not model_file.is_file():
            raise ctx.err("model.file", f"model file {str(model_file)!r} not found")
        file_data = _load_toml(model_file)
        if "schema_version" in file_data:  # a model file (docs/model-file.md)
            if "preset" in table:
                raise ctx.err(
                    "model.preset",
                    f"model.file {str(model_file)!r} is a model file (it has schema_version), "
                    "the nominal model: give it or a preset, not both",
                )
            if model is None:
                model = _read_model_file(ctx, model_file)
            file_data = None
    preset: str | None = None
    if model is not None:
        root = model
    else:
        if "preset" not in table:
            raise ctx.err(
                "model.preset",
                f"missing; give a preset name ({', '.join(preset_names())}) or a model file "
                '(file = "axis.model.toml")',
            )
        preset = ctx.string(table["preset"], "model.preset")
        names = preset_names()
        if preset not in names:
            raise ctx.err(
                "model.preset",
                f"unknown preset {preset!r}"
                f"{did_you_mean(preset, names)}; valid presets: {', '.join(names)}",
            )
        root = preset_system(preset)

    overrides: dict[str, Any] = {}
    if file_data is not None and model_file is not None:  # a file of overrides
        fctx = _Ctx(model_file)
        for path, value in _flatten(file_data).items():
            overrides[path] = _check_override(fctx, root, path, value, path)
    if "overrides" in table:
        inline = _flatten(ctx.table(table["overrides"], "model.overrides"))
        for path, value in inline.items():
            key = f"model.overrides.{path}"
            overrides[path] = _check_override(ctx, root, path, value, key)
    try:
        system = replace_paths(root, overrides)
    except ValueError as exc:  # nanostage.ConfigError is a ValueError
        raise ctx.err("model.overrides", f"the overridden model is invalid: {exc}") from None

    free_raw = table.get("free", [])
    if not isinstance(free_raw, list):
        raise ctx.err("model.free", f"expected an array of dotted paths, got {_tname(free_raw)}")
    free: list[str] = []
    initial: dict[str, float] = {}
    numeric = field_paths(system)
    for i, item in enumerate(free_raw):
        key = f"model.free[{i}]"
        path = ctx.string(item, key)
        if path in free:
            raise ctx.err(key, f"{path!r} is listed twice")
        try:
            value = get_path(system, path)
        except KeyError as exc:
            raise ctx.err(key, str(exc.args[0])) from None
        if path not in numeric:
            raise ctx.err(
                key,
                f"{path!r} is not a numeric parameter (it is {_tname(value)}); free "
                "parameters must be numbers",
            )
        free.append(path)
        initial[path] = float(value)

    bounds: dict[str, tuple[float, float]] = {}
    given = _flatten(ctx.table(table.get("bounds", {}), "model.bounds"))
    for path, value in given.items():
        key = f"model.bounds.{path}"
        if path not in free:
            raise ctx.err(
                key,
                f"bounds for {path!r}, which is not in model.free{did_you_mean(path, free)}",
            )
        if not (isinstance(value, list) and len(value) == 2):
            raise ctx.err(key, f"expected [lower, upper], got {_tname(value)}")
        lo, hi = ctx.number(value[0], key), ctx.number(value[1], key)
        if not lo < hi:
            raise ctx.err(key, f"lower bound {lo:g} must be below the upper bound {hi:g}")
        v = initial[path]
        if not lo <= v <= hi:
            raise ctx.err(
                key,
                f"bounds [{lo:g}, {hi:g}] do not contain the preset value {v:g} of {path!r}",
            )
        bounds[path] = (lo, hi)
    for path in free:
        if path in bounds:
            continue
        v = initial[path]
        if v == 0.0:
            raise ctx.err(
                f"model.bounds.{path}",
                f"the preset value of {path!r} is 0, so the default bounds [value/3, value*3] "
                "are empty; give explicit bounds in [model.bounds]",
            )
        a, b = v / 3.0, v * 3.0
        bounds[path] = (min(a, b), max(a, b))
    if preset is not None:
        travel = PRESET_TRAVEL_M.get(preset, MAX_TRAVEL_M)
    else:  # a model file: the travel of the preset of its plant kind
        travel = PRESET_TRAVEL_M["seed" if isinstance(root.plant, Plant) else "emps"]
    if "travel_m" in table:
        travel = ctx.number(table["travel_m"], "model.travel_m")
        if not 0.0 < travel <= _MAX_TRAVEL_SETTING_M:
            raise ctx.err(
                "model.travel_m",
                f"{travel:g} m is invalid: expected the axis travel in metres, in "
                f"(0, {_MAX_TRAVEL_SETTING_M:g}] (e.g. 0.05 for 50 mm)",
            )
    spec = ModelSpec(
        preset=preset,
        file=model_file,
        overrides=MappingProxyType(overrides),
        free=tuple(free),
        bounds=MappingProxyType({p: bounds[p] for p in free}),
        initial=MappingProxyType(initial),
        travel_m=travel,
        base=None if preset is not None else root,
    )
    return spec, system


def _parse_diagnosis(ctx: _Ctx, raw: Any) -> DiagnosisSpec:
    table = ctx.table(raw, "diagnosis")
    ctx.keys(table, _DIAGNOSIS_KEYS, "diagnosis")
    cand = table.get("candidates", "all")
    if cand == "all":
        candidates = EFFECT_NAMES
    elif isinstance(cand, list):
        out: list[str] = []
        for i, c in enumerate(cand):
            key = f"diagnosis.candidates[{i}]"
            name = ctx.string(c, key)
            if name not in EFFECT_NAMES:
                raise ctx.err(
                    key,
                    f"unknown effect {name!r}{did_you_mean(name, EFFECT_NAMES)}; valid effects: "
                    f"{', '.join(EFFECT_NAMES)}",
                )
            if name in out:
                raise ctx.err(key, f"effect {name!r} is listed twice")
            out.append(name)
        if not out:
            raise ctx.err("diagnosis.candidates", 'empty list; use "all" or name effects')
        candidates = tuple(out)
    else:
        raise ctx.err(
            "diagnosis.candidates", f'expected "all" or a list of effect names, got {_tname(cand)}'
        )
    seed = table.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise ctx.err("diagnosis.seed", f"expected an integer, got {_tname(seed)}")
    scatter = ctx.number(
        table.get("level_scatter", DEFAULT_LEVEL_SCATTER), "diagnosis.level_scatter"
    )
    if not 0.0 <= scatter <= MAX_LEVEL_SCATTER:
        raise ctx.err(
            "diagnosis.level_scatter",
            f"{scatter!r} is out of range: expected a relative friction level scatter in "
            f"[0, {MAX_LEVEL_SCATTER}] (e.g. 0.02 for 2 %; 0 leaves it out)",
        )
    return DiagnosisSpec(candidates=candidates, seed=seed, level_scatter=scatter)


def _parse_experiment(
    ctx: _Ctx,
    raw: Any,
    i: int,
    base_dir: Path,
    controller: ControllerSpec,
    default_kind: str,
    system: Any,
) -> ExperimentSpec:
    key = f"experiment[{i}]"
    table = ctx.table(raw, key)
    ctx.keys(table, ctx.allowed(_EXPERIMENT_KEYS, "experiment"), key)
    for req in ("name", "file"):
        if req not in table:
            raise ctx.err(f"{key}.{req}", "missing (every [[experiment]] needs name and file)")
    name = ctx.string(table["name"], f"{key}.name")
    rel = ctx.string(table["file"], f"{key}.file")
    file = ctx.inside(f"{key}.file", rel, base_dir, f"experiment {name!r}: trace file")
    if not file.is_file():
        raise ctx.err(
            f"{key}.file",
            f"experiment {name!r}: trace file {rel!r} not found (looked for {str(file)!r}, "
            "relative to the manifest's directory)",
        )
    role: Role | None = None
    if "role" in table:
        r = ctx.string(table["role"], f"{key}.role")
        if r == "train":
            role = "train"
        elif r == "validate":
            role = "validate"
        else:
            raise ctx.err(
                f"{key}.role",
                f"experiment {name!r}: unknown role {r!r}{did_you_mean(r, ROLES)}; valid roles: "
                f"{', '.join(ROLES)}",
            )
    valid = ALL_COLUMNS if ctx.purpose == "diagnose" else PREDICTION_COLUMNS
    columns: dict[str, str] | None = None
    if "columns" in table:
        cmap = ctx.table(table["columns"], f"{key}.columns")
        columns = {}
        for std, fname in cmap.items():
            ckey = f"{key}.columns.{std}"
            if std not in valid:
                raise ctx.err(
                    ckey,
                    f"experiment {name!r}: unknown standard column {std!r}"
                    f"{did_you_mean(std, valid)}; valid: {', '.join(valid)} (the map is "
                    "{standard name = name in the file})",
                )
            columns[std] = ctx.string(fname, ckey)
    units = _parse_units(ctx, table, f"{key}.units", name, valid)
    group: str | None = None
    if "group" in table:
        group = ctx.string(table["group"], f"{key}.group")
        if file.suffix.lower() != ".tdms":
            raise ctx.err(
                f"{key}.group",
                f"experiment {name!r}: group applies to .tdms files only, not {rel!r}",
            )
    window: tuple[float, float] | None = None
    if "window_s" in table:
        w = table["window_s"]
        wkey = f"{key}.window_s"
        if not (isinstance(w, list) and len(w) == 2):
            raise ctx.err(wkey, f"expected [start_s, stop_s], got {_tname(w)}")
        start, stop = ctx.number(w[0], wkey), ctx.number(w[1], wkey)
        if not start < stop:
            raise ctx.err(
                wkey, f"experiment {name!r}: start {start:g} s is not before stop {stop:g} s"
            )
        window = (start, stop)
    ctrl = controller
    if "controller" in table:
        ctrl = _parse_controller(
            ctx, table["controller"], f"{key}.controller", controller, default_kind, system
        )
    return ExperimentSpec(
        name=name,
        file=file,
        role=role,
        columns=None if columns is None else MappingProxyType(columns),
        window_s=window,
        controller=ctrl,
        index=i,
        units=units,
        group=group,
    )


def _parse_units(
    ctx: _Ctx, table: Mapping[str, Any], key: str, name: str, valid: Sequence[str]
) -> str | Mapping[str, str] | None:
    """An experiment's ``units``: a length unit for every length column, or a table of
    standard column → unit (lengths and ``time_s``)."""
    if "units" not in table:
        return None
    raw = table["units"]
    lengths = [c for c in POSITION_COLUMNS if c in valid]
    if isinstance(raw, str):
        if raw not in LENGTH_UNITS:
            raise ctx.err(
                key,
                f"experiment {name!r}: unknown length unit {raw!r}"
                f"{did_you_mean(raw, list(LENGTH_UNITS))}"
                f"; valid: {', '.join(LENGTH_UNITS)} (for {', '.join(lengths)}; or a table "
                'such as { position_m = "mm", time_s = "ms" })',
            )
        return raw
    if not isinstance(raw, dict):
        raise ctx.err(key, f"expected a unit or a table of column units, got {_tname(raw)}")
    out: dict[str, str] = {}
    cols = ["time_s", *lengths]
    for std, unit in raw.items():
        ukey = f"{key}.{std}"
        if std not in cols:
            raise ctx.err(
                ukey,
                f"experiment {name!r}: no unit can be declared for {std!r}"
                f"{did_you_mean(std, cols)}; "
                f"units apply to {', '.join(cols)} (other columns are in the unit their name "
                "says)",
            )
        options = TIME_UNITS if std == "time_s" else LENGTH_UNITS
        u = ctx.string(unit, ukey)
        if u not in options:
            raise ctx.err(
                ukey,
                f"experiment {name!r}: unknown unit {u!r} for {std}"
                f"{did_you_mean(u, list(options))}; "
                f"valid: {', '.join(options)}",
            )
        out[std] = u
    return MappingProxyType(out)


def _units_key(units: str | Mapping[str, str] | None) -> str:
    """A hashable form of an experiment's units (for reading each file once)."""
    return repr(units if units is None or isinstance(units, str) else sorted(units.items()))


def check_total_samples(total: int, limits: TraceLimits, spec: ExperimentSpec, path: Path) -> None:
    """Raise :class:`ManifestError` if ``total`` samples (the experiments read so far, up to
    and including ``spec``) exceed ``limits.max_samples_total``."""
    cap = limits.max_samples_total
    if total > cap:
        raise ManifestError(
            f"experiment {spec.name!r} brings the experiments to {total} samples, above the "
            f"limit of {cap} samples per manifest; use fewer or shorter experiments "
            f"(window_s), or {TraceLimits.how_to_raise('max_samples_total')}",
            file=str(path),
            key=f"experiment[{spec.index}]",
        )


def load_manifest(
    path: str | Path,
    *,
    trace_root: str | Path | None = None,
    limits: TraceLimits | None = None,
    model: System | None = None,
) -> Manifest:
    """Load and validate a diagnosis manifest (schema in the module docstring).

    Checks everything that can be checked without reading the traces: keys and types,
    the preset, overrides and free-parameter paths (against the preset's dataclass tree),
    bounds, controller kinds and gains, effect names, roles, unique experiment names,
    column maps and units, that every file it names lies inside the manifest's folder (or
    ``trace_root``) and exists, and windows. Call :meth:`Manifest.experiments` to read
    and check the traces themselves (windows against the trace's time span included).

    Parameters
    ----------
    path : str or Path
        The manifest (TOML).
    trace_root : str or Path, optional
        The folder the files named in the manifest must resolve inside (after symbolic
        links); default: the manifest's folder. Give it to read traces kept elsewhere.
    limits : TraceLimits, optional
        Size limits of the traces (default ``TraceLimits()``).
    model : System, optional
        The nominal model (e.g. :func:`nanostage.load_model`), in place of the manifest's
        ``model.preset`` or model file; the manifest's overrides, free parameters, bounds,
        travel and controller gains apply to it.

    Returns
    -------
    Manifest

    Raises
    ------
    ManifestError
        Naming the manifest file and the key (and the line of a TOML syntax error).
    """
    return _load(path, "diagnose", trace_root, limits, model)


def load_prediction_manifest(
    path: str | Path,
    *,
    trace_root: str | Path | None = None,
    limits: TraceLimits | None = None,
    model: System | None = None,
) -> Manifest:
    """Load and validate a ``nanostage predict`` manifest: the schema of
    :func:`load_manifest` without the diagnosis keys (``model.free``, ``model.bounds``,
    ``[diagnosis]``, ``experiment.role``: errors), the prediction trace columns
    (:data:`~nanostage.diagnosis.traces.PREDICTION_COLUMNS`) in column maps, and experiment
    names that are safe, unique file names (:func:`nanostage.output.check_file_stems`).
    Parameters and errors as in :func:`load_manifest`.
    """
    return _load(path, "predict", trace_root, limits, model)


def _load(
    path: str | Path,
    purpose: Purpose,
    trace_root: str | Path | None,
    limits: TraceLimits | None,
    model: System | None = None,
) -> Manifest:
    p = Path(path).resolve()
    if limits is None:
        limits = TraceLimits()
    elif not isinstance(limits, TraceLimits):
        raise ManifestError(
            f"limits = {limits!r} is invalid: expected a TraceLimits", file=str(path)
        )
    if trace_root is None:
        root = p.parent
    else:
        root = Path(trace_root).expanduser().resolve()
        if not root.is_dir():
            raise ManifestError(
                f"the trace root {str(trace_root)!r} (trace_root=, CLI --trace-root) is not "
                "a folder",
                file=str(path),
            )
    ctx = _Ctx(Path(path), purpose, root)
    data = _load_toml(p, display=str(path))
    top = ctx.allowed(_TOP_KEYS, "")
    for k in data:
        if k not in top:
            if purpose == "predict" and k in _DIAGNOSE_ONLY[""]:
                raise ctx.err(
                    k,
                    "a diagnosis table: nanostage predict does not use it; remove it "
                    f"(valid: {', '.join(top)})",
                )
            hint = did_you_mean(k, top)
            if k == "experiments":
                hint = " (did you mean [[experiment]]?)"
            raise ctx.err(k, f"unknown table{hint}; valid: {', '.join(top)}")
    if "model" not in data:
        raise ctx.err("model", 'missing [model] table (at least: preset = "seed")')
    if model is not None and not isinstance(model, System):
        raise ManifestError(
            f"model = {model!r} is invalid: expected a nanostage.System (e.g. "
            "nanostage.load_model(path))",
            file=str(path),
        )
    model_spec, system = _parse_model(ctx, data["model"], p.parent, model)
    have = {f.name for f in dataclasses.fields(system.controller)}
    default_kind = next(
        (k for k, g in CONTROLLER_GAINS.items() if set(g) <= have),
        PRESET_CONTROLLER_KIND.get(model_spec.preset or "", "fpga_pid"),
    )
    controller = _parse_controller(
        ctx, data.get("controller", {}), "controller", None, default_kind, system
    )
    diagnosis = _parse_diagnosis(ctx, data.get("diagnosis", {}))

    raw_exps = data.get("experiment")
    if raw_exps is None:
        what = "the diagnosis" if purpose == "diagnose" else "the prediction"
        raise ctx.err("experiment", f"no [[experiment]] entries; {what} needs at least one")
    if isinstance(raw_exps, dict):
        raise ctx.err("experiment", "write experiments as [[experiment]] (an array of tables)")
    if not isinstance(raw_exps, list) or not raw_exps:
        raise ctx.err("experiment", "expected one or more [[experiment]] tables")
    specs: list[ExperimentSpec] = []
    seen: dict[str, int] = {}
    for i, raw in enumerate(raw_exps):
        spec = _parse_experiment(ctx, raw, i, p.parent, controller, default_kind, system)
        if purpose == "predict":
            try:  # each name becomes the file name of its prediction
                check_file_stems([*seen, spec.name], "name")
            except OutputError as exc:
                raise ctx.err(f"experiment[{i}].name", str(exc)) from None
        if spec.name in seen:
            raise ctx.err(
                f"experiment[{i}].name",
                f"duplicate experiment name {spec.name!r} (also experiment[{seen[spec.name]}])",
            )
        seen[spec.name] = i
        specs.append(spec)
    with_role = [s for s in specs if s.role is not None]
    if with_role and len(with_role) != len(specs):
        missing = next(s for s in specs if s.role is None)
        raise ctx.err(
            f"experiment[{missing.index}].role",
            f"experiment {missing.name!r} has no role while others do; give every "
            "experiment a role (train or validate) or none (leave-one-out folds)",
        )
    if with_role and not any(s.role == "train" for s in specs):
        raise ctx.err("experiment", 'no experiment has role = "train"')
    return Manifest(
        path=p,
        model=model_spec,
        controller=controller,
        diagnosis=diagnosis,
        experiment_specs=tuple(specs),
        limits=limits,
        purpose=purpose,
    )
