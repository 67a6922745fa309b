"""The model file: a whole :class:`nanostage.System` as TOML (docs/model-file.md).

The tables follow the dataclass tree and the keys are the dataclass field names, which carry
their units (``[plant.motor] resistance_ohm = 3.4``). Where a field takes one of several
dataclasses (the plant, the controller, the table friction of the effects) the table names
its class with ``kind``. Reading and writing are generic over :func:`dataclasses.fields` and
the type hints, so a new field or effect needs no change here.

Floats are written as their shortest repr, which reads back to the same bits:
``load_model(p)`` after ``save_model(s, p)`` is equal to ``s`` bit for bit.

Every error is a :class:`ModelFileError` (a :class:`nanostage.ConfigError`) raised before
anything runs, naming the file and the dotted key: an unknown key (with the closest valid
one), a missing required key or table, a value of the wrong type, a value out of range (the
dataclasses' own validation, with the key path of the file), a newer ``schema_version``.
"""

from __future__ import annotations

import dataclasses
import math
import os
import sys
import tempfile
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final, Literal, Union

import tomli_w

from ._core import ConfigError
from .config import (
    CascadeController,
    DahlFriction,
    ForceDrivePlant,
    FpgaPid,
    Plant,
    System,
    did_you_mean,
)
from .config import field_paths as _numeric_paths
from .effects import Effects, Gms, LuGre, StaticFrictionMap

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

__all__ = [
    "IDENTIFIED_KEYS",
    "KINDS",
    "SCHEMA_VERSION",
    "IdentifiedParameter",
    "ModelDocument",
    "ModelFileError",
    "load_model",
    "load_model_file",
    "model_to_toml",
    "parse_model",
    "save_model",
]

#: The newest schema this module reads and the one it writes.
SCHEMA_VERSION: Final = 1

#: The ``kind`` of each dataclass that shares a field with others (the plant, the
#: controller, the table friction of the effects).
KINDS: Final[Mapping[type, str]] = types.MappingProxyType(
    {
        Plant: "rigid_axis",
        ForceDrivePlant: "force_drive",
        FpgaPid: "fpga_pid",
        CascadeController: "cascade",
        StaticFrictionMap: "static_map",
        LuGre: "lugre",
        Gms: "gms",
    }
)

#: The keys of an ``[identified."dotted.path"]`` entry.
IDENTIFIED_KEYS: Final = ("std_error", "lower", "upper")

#: Dataclasses whose fields at their default are left out of the file (an effect at its
#: default is switched off).
_SPARSE: Final = frozenset({Effects})

#: Fields left out of the file at their default (0: a symmetric friction law), so that a
#: model without them reads and writes the same text as before they existed.
_SPARSE_FIELDS: Final[Mapping[type, frozenset[str]]] = types.MappingProxyType(
    {
        DahlFriction: frozenset({"asymmetry"}),
        LuGre: frozenset({"asymmetry"}),
        Gms: frozenset({"asymmetry"}),
    }
)
_TOP: Final = ("schema_version", "provenance", "identified")


class ModelFileError(ConfigError):
    """A model file that cannot be read: the message names the file and the dotted key."""


@dataclass(frozen=True, slots=True, kw_only=True)
class IdentifiedParameter:
    """What an identification says about one parameter: its standard error and the bounds
    of the fit (each in the parameter's unit, ``None`` when not given)."""

    std_error: float | None = None
    lower: float | None = None
    upper: float | None = None


@dataclass(frozen=True, slots=True, kw_only=True)
class ModelDocument:
    """A model file read whole: the system, the free-form ``[provenance]`` table and the
    ``[identified."dotted.path"]`` entries keyed by the parameter's dotted path."""

    system: System
    provenance: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    identified: Mapping[str, IdentifiedParameter] = dataclasses.field(default_factory=dict)


# --------------------------------------------------------------------------------------------
# Type hints
# --------------------------------------------------------------------------------------------

_HINTS: dict[type, dict[str, Any]] = {}


def _hints(cls: type) -> dict[str, Any]:
    if cls not in _HINTS:
        _HINTS[cls] = typing.get_type_hints(cls)
    return _HINTS[cls]


def _is_union(hint: Any) -> bool:
    return typing.get_origin(hint) in (Union, types.UnionType)


def _split_optional(hint: Any) -> tuple[Any, bool]:
    """``(hint without None, whether None was allowed)``."""
    if _is_union(hint):
        args = typing.get_args(hint)
        rest = tuple(a for a in args if a is not type(None))
        if len(rest) < len(args):
            return (rest[0] if len(rest) == 1 else Union[rest], True)  # noqa: UP007
    return hint, False


def _union_classes(hint: Any) -> tuple[type, ...] | None:
    """The dataclasses of a union of several dataclasses, else ``None``."""
    if _is_union(hint):
        args = typing.get_args(hint)
        if all(dataclasses.is_dataclass(a) for a in args):
            return tuple(args)
    return None


def _kind_of(cls: type) -> str:
    return KINDS.get(cls, cls.__name__)


def _describe(hint: Any) -> str:
    """What the file must hold for a hint, e.g. ``a number``."""
    inner, _ = _split_optional(hint)
    classes = _union_classes(inner)
    if classes is not None or dataclasses.is_dataclass(inner):
        return "a table"
    if typing.get_origin(inner) is Literal:
        return "one of " + ", ".join(repr(a) for a in typing.get_args(inner))
    if typing.get_origin(inner) is tuple:
        return "an array"
    return {bool: "true or false", int: "an integer", float: "a number", str: "a string"}.get(
        inner, str(inner)
    )


# --------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------


def _encode(value: Any, hint: Any) -> Any:
    inner, _ = _split_optional(hint)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        cls = type(value)
        out: dict[str, Any] = {}
        if _union_classes(inner) is not None:
            out["kind"] = _kind_of(cls)
        hints = _hints(cls)
        for f in dataclasses.fields(value):
            v = getattr(value, f.name)
            if v is None:
                continue
            enc = _encode(v, hints[f.name])
            sparse = cls in _SPARSE or f.name in _SPARSE_FIELDS.get(cls, ())
            if sparse and _is_default(f, enc, hints[f.name]):
                continue
            out[f.name] = enc
        return out
    if isinstance(value, tuple):
        args = typing.get_args(inner)
        if len(args) == 2 and args[1] is Ellipsis:
            return [_encode(v, args[0]) for v in value]
        return [_encode(v, a) for v, a in zip(value, args, strict=True)]
    if inner is float and isinstance(value, int | float) and not isinstance(value, bool):
        return float(value)
    if isinstance(value, bool | int | float | str):
        return value
    raise ModelFileError(f"{value!r} ({type(value).__name__}) cannot be written to a model file")


def _is_default(f: dataclasses.Field[Any], encoded: Any, hint: Any) -> bool:
    if f.default is not dataclasses.MISSING:
        default = f.default
    elif f.default_factory is not dataclasses.MISSING:
        default = f.default_factory()
    else:
        return False
    if default is None:
        return False
    # repr tells -0.0 from 0.0, which == does not
    return repr(_encode(default, hint)) == repr(encoded)


def model_to_toml(
    system: System,
    *,
    provenance: Mapping[str, Any] | None = None,
    identified: Mapping[str, IdentifiedParameter | Mapping[str, float]] | None = None,
) -> str:
    """The model file's text for ``system`` (see :func:`save_model`)."""
    if not isinstance(system, System):
        raise TypeError(f"system must be a nanostage.System, not {type(system).__name__}")
    doc: dict[str, Any] = {"schema_version": SCHEMA_VERSION}
    doc.update(_encode(system, System))
    if provenance:
        doc["provenance"] = dict(provenance)
    if identified:
        paths = _numeric_paths(system)
        table: dict[str, dict[str, float]] = {}
        for path, entry in identified.items():
            if path not in paths:
                raise ModelFileError(
                    f"identified: {path!r} is not a numeric parameter of the model"
                    f"{did_you_mean(path, paths)}"
                )
            if isinstance(entry, IdentifiedParameter):
                raw: Mapping[str, Any] = {
                    k: getattr(entry, k) for k in IDENTIFIED_KEYS if getattr(entry, k) is not None
                }
            else:
                raw = entry
            table[path] = _identified_entry(raw, f'identified."{path}"')
        doc["identified"] = table
    try:
        text = tomli_w.dumps(doc)
    except TypeError as exc:
        raise ModelFileError(f"provenance cannot be written as TOML: {exc}") from None
    return f"# nanostage model file, schema {SCHEMA_VERSION} (docs/model-file.md)\n\n{text}"


def save_model(
    system: System,
    path: str | os.PathLike[str],
    *,
    provenance: Mapping[str, Any] | None = None,
    identified: Mapping[str, IdentifiedParameter | Mapping[str, float]] | None = None,
) -> Path:
    """Write ``system`` as a model file (whole or not at all); returns the path.

    Parameters
    ----------
    system : System
        The model.
    path : path-like
        The file (conventionally ``*.model.toml`` or ``model.toml``).
    provenance : mapping, optional
        Free text and numbers (data, command, version, fit statistics): the ``[provenance]``
        table.
    identified : mapping of str to IdentifiedParameter, optional
        Standard error and bounds per dotted parameter path: the ``[identified."path"]``
        tables.
    """
    text = model_to_toml(system, provenance=provenance, identified=identified)
    target = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return target


# --------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------


def _join(path: str, key: str) -> str:
    return f"{path}.{key}" if path else key


def _type_name(raw: Any) -> str:
    return {dict: "table", list: "array", bool: "boolean", int: "integer", float: "float"}.get(
        type(raw), type(raw).__name__
    )


class _Reader:
    def __init__(self, source: str) -> None:
        self.source = source

    def error(self, message: str) -> ModelFileError:
        return ModelFileError(f"{self.source}: {message}")

    def wrong_type(self, path: str, raw: Any, hint: Any) -> ModelFileError:
        shown = repr(raw) if not isinstance(raw, dict | list) else _type_name(raw)
        return self.error(
            f"{path} = {shown} ({_type_name(raw)}) is invalid: expected {_describe(hint)}"
        )

    def value(self, raw: Any, hint: Any, path: str) -> Any:
        inner, _ = _split_optional(hint)
        classes = _union_classes(inner)
        if classes is not None:
            if not isinstance(raw, dict):
                raise self.wrong_type(path, raw, inner)
            kinds = {_kind_of(c): c for c in classes}
            if "kind" not in raw:
                raise self.error(
                    f"missing required key {_join(path, 'kind')} (one of "
                    f"{', '.join(repr(k) for k in kinds)})"
                )
            kind = raw["kind"]
            if kind not in kinds:
                raise self.error(
                    f"{_join(path, 'kind')} = {kind!r} is invalid: expected one of "
                    f"{', '.join(repr(k) for k in kinds)}{did_you_mean(str(kind), list(kinds))}"
                )
            return self.dataclass(kinds[kind], {k: v for k, v in raw.items() if k != "kind"}, path)
        if dataclasses.is_dataclass(inner):
            if not isinstance(raw, dict):
                raise self.wrong_type(path, raw, inner)
            assert isinstance(inner, type)
            return self.dataclass(inner, raw, path)
        origin = typing.get_origin(inner)
        if origin is Literal:
            choices = typing.get_args(inner)
            if not isinstance(raw, str) or raw not in choices:
                hint_text = did_you_mean(raw, choices) if isinstance(raw, str) else ""
                raise self.error(
                    f"{path} = {raw!r} is invalid: expected {_describe(inner)}{hint_text}"
                )
            return raw
        if origin is tuple:
            if not isinstance(raw, list):
                raise self.wrong_type(path, raw, inner)
            args = typing.get_args(inner)
            if len(args) == 2 and args[1] is Ellipsis:
                return tuple(self.value(v, args[0], f"{path}[{i}]") for i, v in enumerate(raw))
            if len(raw) != len(args):
                raise self.error(f"{path} has {len(raw)} entries: expected {len(args)}")
            return tuple(
                self.value(v, a, f"{path}[{i}]")
                for i, (v, a) in enumerate(zip(raw, args, strict=True))
            )
        if inner is bool:
            if not isinstance(raw, bool):
                raise self.wrong_type(path, raw, inner)
            return raw
        if inner is int:
            if not isinstance(raw, int) or isinstance(raw, bool):
                raise self.wrong_type(path, raw, inner)
            return raw
        if inner is float:
            if not isinstance(raw, int | float) or isinstance(raw, bool):
                raise self.wrong_type(path, raw, inner)
            return float(raw)
        if inner is str:
            if not isinstance(raw, str):
                raise self.wrong_type(path, raw, inner)
            return raw
        raise self.error(f"{path}: cannot read a value of type {inner}")  # pragma: no cover

    def dataclass(self, cls: type, raw: dict[str, Any], path: str) -> Any:
        hints = _hints(cls)
        fields = {f.name: f for f in dataclasses.fields(cls)}
        for key in raw:
            if key not in fields:
                raise self.unknown(cls, key, list(fields), path)
        kwargs: dict[str, Any] = {}
        for name, f in fields.items():
            key = _join(path, name)
            if name not in raw:
                if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                    inner, _ = _split_optional(hints[name])
                    table = _union_classes(inner) is not None or dataclasses.is_dataclass(inner)
                    what = f"table [{key}]" if table else f"key {key} ({_describe(hints[name])})"
                    raise self.error(f"missing required {what}")
                continue
            kwargs[name] = self.value(raw[name], hints[name], key)
        try:
            return cls(**kwargs)
        except ConfigError as exc:
            message = _keyed(str(exc), path, list(fields))
            if cls is System and not _in_file(raw, message.split(" ", 1)[0]):
                on = ", ".join(raw.get("effects", {})) or "none"
                message += (
                    f" (a check of the plant the effects build; the [effects] keys given: {on})"
                )
            raise self.error(message) from None

    def unknown(self, cls: type, key: str, valid: list[str], path: str) -> ModelFileError:
        if cls is Effects:
            return self.error(
                f"unknown effect {_join(path, key)}{did_you_mean(key, valid)}; the effects are: "
                f"{', '.join(valid)}"
            )
        where = f"[{path}]" if path else "the top level"
        return self.error(
            f"unknown key {_join(path, key)}{did_you_mean(key, valid)}; the keys of {where} "
            f"({cls.__name__}) are: {', '.join(valid)}"
        )


def _keyed(message: str, path: str, names: list[str]) -> str:
    """A dataclass's validation message with the key path of the file: the message starts
    with a path relative to the dataclass (``table.mass_kg = ...``), which is prefixed."""
    first = message.split(" ", 1)[0]
    head = first.split(".", 1)[0].split("[", 1)[0]
    if not path:
        return message
    if head in names:
        return f"{path}.{message}"
    return f"{path}: {message}"


def _in_file(raw: Any, path: str) -> bool:
    """Whether a dotted key path (``a.b[0].c``) is a key of the file's tables."""
    cur = raw
    for part in path.split("."):
        name, _, index = part.partition("[")
        if not isinstance(cur, dict) or name not in cur:
            return False
        cur = cur[name]
        while index:
            i, _, index = index.partition("]")
            index = index.lstrip("[")
            if not isinstance(cur, list) or not i.isdigit() or int(i) >= len(cur):
                return False
            cur = cur[int(i)]
    return True


def _identified_entry(raw: Any, path: str) -> dict[str, float]:
    if not isinstance(raw, Mapping):
        raise ModelFileError(f"{path} is invalid: expected a table of {', '.join(IDENTIFIED_KEYS)}")
    out: dict[str, float] = {}
    for k, v in raw.items():
        if k not in IDENTIFIED_KEYS:
            raise ModelFileError(
                f"unknown key {path}.{k}{did_you_mean(str(k), IDENTIFIED_KEYS)}; the keys "
                f"are: {', '.join(IDENTIFIED_KEYS)}"
            )
        if not isinstance(v, int | float) or isinstance(v, bool) or math.isnan(v):
            raise ModelFileError(f"{path}.{k} = {v!r} is invalid: expected a number")
        out[k] = float(v)
    if "std_error" in out and not out["std_error"] >= 0:
        raise ModelFileError(
            f"{path}.std_error = {out['std_error']!r} is invalid: expected at least 0"
        )
    if "lower" in out and "upper" in out and not out["lower"] <= out["upper"]:
        raise ModelFileError(f"{path}: lower = {out['lower']!r} is above upper = {out['upper']!r}")
    return out


def parse_model(text: str, *, source: str = "<model>") -> ModelDocument:
    """Read a model file's text (``source`` names it in the errors)."""
    r = _Reader(source)
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise r.error(f"not valid TOML: {exc}") from None
    if "schema_version" not in raw:
        raise r.error(
            f"missing required key schema_version (this nanostage writes {SCHEMA_VERSION})"
        )
    version = raw["schema_version"]
    if not isinstance(version, int) or isinstance(version, bool) or version < 1:
        raise r.error(
            f"schema_version = {version!r} is invalid: expected an integer in [1, {SCHEMA_VERSION}]"
        )
    if version > SCHEMA_VERSION:
        raise r.error(
            f"schema_version = {version} is newer than this nanostage reads (at most "
            f"{SCHEMA_VERSION}): update nanostage"
        )
    body = {k: v for k, v in raw.items() if k not in _TOP}
    names = [f.name for f in dataclasses.fields(System)]
    for key in body:
        if key not in names:
            raise r.unknown(System, key, [*_TOP, *names], "")
    system = r.dataclass(System, body, "")
    provenance = raw.get("provenance", {})
    if not isinstance(provenance, dict):
        raise r.error(f"provenance is a {_type_name(provenance)}: expected a table")
    identified: dict[str, IdentifiedParameter] = {}
    table = raw.get("identified", {})
    if not isinstance(table, dict):
        raise r.error(f"identified is a {_type_name(table)}: expected a table")
    paths = _numeric_paths(system)
    for path, entry in table.items():
        if path not in paths:
            raise r.error(
                f'identified."{path}" is not a numeric parameter of the model'
                f"{did_you_mean(path, paths)}"
            )
        try:
            identified[path] = IdentifiedParameter(
                **_identified_entry(entry, f'identified."{path}"')
            )
        except ModelFileError as exc:
            raise r.error(str(exc)) from None
    return ModelDocument(system=system, provenance=provenance, identified=identified)


def load_model_file(path: str | os.PathLike[str]) -> ModelDocument:
    """Read a model file whole: the system, its provenance and the identified parameters."""
    p = Path(path)
    with p.open("rb") as fh:
        data = fh.read()
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ModelFileError(f"{p}: not UTF-8 text (byte offset {exc.start})") from None
    return parse_model(text, source=str(p))


def load_model(path: str | os.PathLike[str]) -> System:
    """The :class:`nanostage.System` of a model file (provenance and identified entries are
    checked and left out; :func:`load_model_file` returns them)."""
    return load_model_file(path).system
