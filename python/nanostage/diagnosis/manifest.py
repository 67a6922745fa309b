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
    preset = "seed"                 # required: a preset name (see PRESET_NAMES())
    file = "model.toml"             # optional: a TOML file of overrides, relative to the
                                    #   manifest, e.g.  [plant.table]  mass_kg = 0.8
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
    file = "traces/step_100um_1.csv"  # required, relative to the manifest (CSV, .npz, .mat)
    role = "train"                  # optional: "train" | "validate"; all experiments or none.
                                    #   None: leave-one-experiment-out folds
    columns = { position_m = "qm" } # optional column map {standard name: name in the file}
    window_s = [0.0, 12.0]          # optional time window [start, stop) in s
    controller = { kp = 12.0 }      # optional per-experiment controller: merged over the
                                    #   default (a different `kind` replaces it)

Unknown keys anywhere are errors (with a "did you mean" hint), so typos do not pass
silently.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import re
import sys
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Any, Final, Literal

from .. import presets
from ..effect_names import EFFECT_NAMES
from ..experiment import Experiment
from .traces import ALL_COLUMNS, TraceError, cut_window, read_trace

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
    "field_paths",
    "get_path",
    "load_manifest",
    "preset_names",
    "preset_system",
    "replace_paths",
]

Role = Literal["train", "validate"]
#: Valid experiment roles.
ROLES: Final[tuple[str, ...]] = ("train", "validate")
#: Controller kinds and the gains each takes.
CONTROLLER_GAINS: Final[Mapping[str, tuple[str, ...]]] = MappingProxyType(
    {"fpga_pid": ("kp", "ki", "kd"), "cascade": ("kp_per_s", "kv_v_s_per_m")}
)
#: The controller kind of each preset (used when the manifest gives none).
_PRESET_CONTROLLER_KIND: Final[Mapping[str, str]] = MappingProxyType(
    {"seed": "fpga_pid", "emps": "cascade"}
)

_TOP_KEYS: Final = ("model", "controller", "diagnosis", "experiment")
_MODEL_KEYS: Final = ("preset", "file", "free", "overrides", "bounds")
_DIAGNOSIS_KEYS: Final = ("candidates", "seed")
_EXPERIMENT_KEYS: Final = ("name", "file", "role", "columns", "window_s", "controller")


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
# Dotted paths into the configuration dataclass tree
# --------------------------------------------------------------------------------------------


def preset_names() -> tuple[str, ...]:
    """Names a manifest's ``model.preset`` may take.

    ``nanostage.presets.PRESETS`` (a mapping name → zero-argument factory) is used when the
    presets module defines it; otherwise the only preset is ``"seed"``.
    """
    return tuple(_preset_factories())


def _preset_factories() -> dict[str, Callable[[], Any]]:
    registry = getattr(presets, "PRESETS", None)
    if isinstance(registry, Mapping):
        return {str(k): v for k, v in registry.items()}
    return {"seed": presets.seed}


def preset_system(name: str) -> Any:
    """The configuration (e.g. a :class:`nanostage.System`) of the preset ``name``.

    Raises
    ------
    KeyError
        If there is no such preset.
    """
    return _preset_factories()[name]()


def _hint(word: str, options: Sequence[str]) -> str:
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
                f"{where} ({type(cur).__name__}) has no field {part!r}{_hint(part, names)}; "
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
    preset : str
        Preset name.
    file : Path or None
        The overrides file, resolved.
    overrides : mapping of str to Any
        Dotted path → value (the file's, then the manifest's ``[model.overrides]``).
    free : tuple of str
        Free parameters (dotted paths), in manifest order.
    bounds : mapping of str to (float, float)
        ``(lower, upper)`` of every free parameter (defaults filled in).
    initial : mapping of str to float
        Value of every free parameter in the preset with the overrides applied.
    """

    preset: str
    file: Path | None
    overrides: Mapping[str, Any]
    free: tuple[str, ...]
    bounds: Mapping[str, tuple[float, float]]
    initial: Mapping[str, float]


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


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class DiagnosisSpec:
    """The ``[diagnosis]`` table: candidate effects (resolved) and the random seed."""

    candidates: tuple[str, ...]
    seed: int


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
    """

    path: Path
    model: ModelSpec
    controller: ControllerSpec
    diagnosis: DiagnosisSpec
    experiment_specs: tuple[ExperimentSpec, ...]

    def system(self, experiment: ExperimentSpec | None = None) -> Any:
        """The preset with the model overrides and the controller gains applied.

        The gains are those of ``experiment`` (default: the manifest's default controller),
        set as ``controller.<gain>``; gains the manifest does not give keep the preset's
        values. The controller kind was checked against the preset's controller at load.
        """
        system = replace_paths(preset_system(self.model.preset), self.model.overrides)
        ctrl = self.controller if experiment is None else experiment.controller
        gains = {f"controller.{k}": v for k, v in ctrl.gains.items()}
        return replace_paths(system, gains) if gains else system

    def experiments(self) -> list[tuple[ExperimentSpec, Experiment]]:
        """Read and check every experiment's trace (each file once).

        Raises
        ------
        ManifestError
            Wrapping the :class:`~nanostage.diagnosis.traces.TraceError` (available as
            ``__cause__``), with the experiment's key and name.
        """
        cache: dict[tuple[Path, tuple[tuple[str, str], ...]], Experiment] = {}
        out: list[tuple[ExperimentSpec, Experiment]] = []
        for spec in self.experiment_specs:
            cols = tuple(sorted((spec.columns or {}).items()))
            try:
                whole = cache.get((spec.file, cols))
                if whole is None:
                    whole = read_trace(spec.file, columns=spec.columns, name=spec.name)
                    cache[(spec.file, cols)] = whole
                exp = whole if spec.window_s is None else cut_window(whole, spec.window_s)
            except TraceError as exc:
                raise ManifestError(
                    f"experiment {spec.name!r}: {exc}",
                    file=str(self.path),
                    key=f"experiment[{spec.index}]",
                ) from exc
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


def _load_toml(path: Path, display: str | None = None) -> dict[str, Any]:
    file = display or str(path)
    if not path.is_file():
        raise ManifestError(
            "no such file" if not path.exists() else "not a regular file", file=file
        )
    try:
        with path.open("rb") as fh:
            return tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        m = _LINE_RE.search(str(exc))
        raise ManifestError(
            f"TOML syntax error: {exc}", file=file, line=int(m.group(1)) if m else None
        ) from None
    except UnicodeDecodeError as exc:
        raise ManifestError(f"not UTF-8 text: {exc}", file=file) from None


class _Ctx:
    """Error factory bound to a file."""

    def __init__(self, file: Path) -> None:
        self.file = str(file)

    def err(self, key: str | None, message: str) -> ManifestError:
        return ManifestError(message, file=self.file, key=key)

    def table(self, value: Any, key: str) -> dict[str, Any]:
        if not isinstance(value, dict):
            raise self.err(key, f"expected a table, got {_tname(value)}")
        return value

    def keys(self, table: Mapping[str, Any], allowed: Sequence[str], key: str) -> None:
        for k in table:
            if k not in allowed:
                where = f"{key}.{k}" if key else k
                raise self.err(
                    where,
                    f"unknown key{_hint(k, allowed)}; valid keys: {', '.join(allowed)}",
                )

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
            f"unknown controller kind {kind!r}{_hint(kind, list(CONTROLLER_GAINS))}; valid "
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


def _parse_model(ctx: _Ctx, raw: Any, base_dir: Path) -> tuple[ModelSpec, Any]:
    table = ctx.table(raw, "model")
    ctx.keys(table, _MODEL_KEYS, "model")
    if "preset" not in table:
        raise ctx.err("model.preset", f"missing; give a preset name ({', '.join(preset_names())})")
    preset = ctx.string(table["preset"], "model.preset")
    names = preset_names()
    if preset not in names:
        raise ctx.err(
            "model.preset",
            f"unknown preset {preset!r}{_hint(preset, names)}; valid presets: {', '.join(names)}",
        )
    root = preset_system(preset)

    overrides: dict[str, Any] = {}
    model_file: Path | None = None
    if "file" in table:
        model_file = (base_dir / ctx.string(table["file"], "model.file")).resolve()
        if not model_file.is_file():
            raise ctx.err("model.file", f"model overrides file {str(model_file)!r} not found")
        fctx = _Ctx(model_file)
        for path, value in _flatten(_load_toml(model_file)).items():
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
                f"bounds for {path!r}, which is not in model.free{_hint(path, free)}",
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
    spec = ModelSpec(
        preset=preset,
        file=model_file,
        overrides=MappingProxyType(overrides),
        free=tuple(free),
        bounds=MappingProxyType({p: bounds[p] for p in free}),
        initial=MappingProxyType(initial),
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
                    f"unknown effect {name!r}{_hint(name, EFFECT_NAMES)}; valid effects: "
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
    return DiagnosisSpec(candidates=candidates, seed=seed)


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
    ctx.keys(table, _EXPERIMENT_KEYS, key)
    for req in ("name", "file"):
        if req not in table:
            raise ctx.err(f"{key}.{req}", "missing (every [[experiment]] needs name and file)")
    name = ctx.string(table["name"], f"{key}.name")
    rel = ctx.string(table["file"], f"{key}.file")
    file = (base_dir / rel).resolve()
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
                f"experiment {name!r}: unknown role {r!r}{_hint(r, ROLES)}; valid roles: "
                f"{', '.join(ROLES)}",
            )
    columns: dict[str, str] | None = None
    if "columns" in table:
        cmap = ctx.table(table["columns"], f"{key}.columns")
        columns = {}
        for std, fname in cmap.items():
            ckey = f"{key}.columns.{std}"
            if std not in ALL_COLUMNS:
                raise ctx.err(
                    ckey,
                    f"experiment {name!r}: unknown standard column {std!r}"
                    f"{_hint(std, ALL_COLUMNS)}; valid: {', '.join(ALL_COLUMNS)} (the map is "
                    "{standard name = name in the file})",
                )
            columns[std] = ctx.string(fname, ckey)
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
    )


def load_manifest(path: str | Path) -> Manifest:
    """Load and validate a diagnosis manifest (schema in the module docstring).

    Checks everything that can be checked without reading the traces: keys and types,
    the preset, overrides and free-parameter paths (against the preset's dataclass tree),
    bounds, controller kinds and gains, effect names, roles, unique experiment names,
    that every trace file exists, and windows. Call :meth:`Manifest.experiments` to read
    and check the traces themselves (windows against the trace's time span included).

    Parameters
    ----------
    path : str or Path
        The manifest (TOML).

    Returns
    -------
    Manifest

    Raises
    ------
    ManifestError
        Naming the manifest file and the key (and the line of a TOML syntax error).
    """
    p = Path(path).resolve()
    ctx = _Ctx(Path(path))
    data = _load_toml(p, display=str(path))
    for k in data:
        if k not in _TOP_KEYS:
            hint = _hint(k, _TOP_KEYS)
            if k == "experiments":
                hint = " (did you mean [[experiment]]?)"
            raise ctx.err(k, f"unknown table{hint}; valid: {', '.join(_TOP_KEYS)}")
    if "model" not in data:
        raise ctx.err("model", 'missing [model] table (at least: preset = "seed")')
    model, system = _parse_model(ctx, data["model"], p.parent)
    have = {f.name for f in dataclasses.fields(system.controller)}
    default_kind = next(
        (k for k, g in CONTROLLER_GAINS.items() if set(g) <= have),
        _PRESET_CONTROLLER_KIND.get(model.preset, "fpga_pid"),
    )
    controller = _parse_controller(
        ctx, data.get("controller", {}), "controller", None, default_kind, system
    )
    diagnosis = _parse_diagnosis(ctx, data.get("diagnosis", {}))

    raw_exps = data.get("experiment")
    if raw_exps is None:
        raise ctx.err("experiment", "no [[experiment]] entries; the diagnosis needs at least one")
    if isinstance(raw_exps, dict):
        raise ctx.err("experiment", "write experiments as [[experiment]] (an array of tables)")
    if not isinstance(raw_exps, list) or not raw_exps:
        raise ctx.err("experiment", "expected one or more [[experiment]] tables")
    specs: list[ExperimentSpec] = []
    seen: dict[str, int] = {}
    for i, raw in enumerate(raw_exps):
        spec = _parse_experiment(ctx, raw, i, p.parent, controller, default_kind, system)
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
        model=model,
        controller=controller,
        diagnosis=diagnosis,
        experiment_specs=tuple(specs),
    )
