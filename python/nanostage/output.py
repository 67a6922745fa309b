"""Output folders written whole or not at all, strict JSON and safe file names.

Every command that writes a folder (``--out``) goes through :func:`staged_output`:

* the folder is checked **before any work** (:func:`check_output_dir`): it must be missing,
  empty, or a folder an earlier nanostage run wrote (it holds :data:`RUN_MANIFEST`); an
  existing file, a folder of other files or an unwritable parent is a :class:`OutputError`
  naming the path;
* the run writes into a hidden temporary folder beside it; only when the run succeeds is a
  manifest of its files written (last) and the temporary folder renamed into place, the
  previous run's folder being removed. An interrupted or failed run leaves the previous
  output as it was and no partial folder (the temporary one is removed; a run killed
  outright leaves only a hidden ``.NAME.partial-*`` folder beside it, never a mix).

JSON is written strict (:func:`write_json`): NaN and infinities become ``null``, never the
non-standard ``NaN``/``Infinity`` tokens.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import secrets
import shutil
import tempfile
import time
from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Final, TextIO

import numpy as np

__all__ = [
    "PROGRESS_REFRESH_S",
    "RUN_MANIFEST",
    "OutputError",
    "ProgressBar",
    "check_file_stems",
    "check_output_dir",
    "staged_output",
    "to_jsonable",
    "write_json",
]

RUN_MANIFEST: Final = "nanostage-run.json"
"""The file a finished run writes last into its output folder: the command and its files."""

#: Seconds between two progress-bar updates.
PROGRESS_REFRESH_S: Final[float] = 0.1
#: Width of the progress bar in characters.
_BAR_WIDTH: Final[int] = 30

_STEM: Final = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,99}$")


class OutputError(ValueError):
    """An output folder or output file name that cannot be used, found before any work."""


def to_jsonable(obj: Any) -> Any:
    """A JSON-serialisable copy: numpy → Python numbers/lists, NaN/inf → None, dataclasses
    via ``to_dict()`` (or :func:`dataclasses.asdict`), paths → str, tuples/sets → lists,
    mapping keys → str."""
    if obj is None or isinstance(obj, bool | str):
        return obj
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, int | np.integer):
        return int(obj)
    if isinstance(obj, float | np.floating):
        v = float(obj)
        return v if math.isfinite(v) else None
    if isinstance(obj, np.ndarray):
        return [to_jsonable(v) for v in obj.tolist()] if obj.ndim else to_jsonable(obj.item())
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, Mapping):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        to_dict = getattr(obj, "to_dict", None)
        if callable(to_dict):
            return to_jsonable(to_dict())
        return to_jsonable({f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)})
    if isinstance(obj, set | frozenset):
        return [to_jsonable(v) for v in sorted(obj, key=str)]
    if isinstance(obj, list | tuple):
        return [to_jsonable(v) for v in obj]
    raise TypeError(f"cannot write {type(obj).__name__} to JSON: {obj!r:.80}")


def write_json(data: Any, path: str | Path, *, indent: int = 2) -> Path:
    """Write ``to_jsonable(data)`` as indented UTF-8 JSON (strict: no NaN tokens)."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(to_jsonable(data), indent=indent, allow_nan=False, ensure_ascii=False)
    p.write_text(text + "\n", encoding="utf-8")
    return p


def check_file_stems(names: Iterable[str], field: str) -> list[str]:
    """Check names that become file names inside an output folder.

    Each must be 1–100 characters of letters, digits, ``_``, ``-`` and ``.``, start with a
    letter or digit (so no ``..``, no hidden file, no path separator), and be unique
    (case-insensitively, for case-insensitive file systems).

    Raises
    ------
    OutputError
        Naming ``field``, the offending name and the rule.
    """
    out: list[str] = []
    seen: dict[str, str] = {}
    for name in names:
        if not isinstance(name, str) or not _STEM.match(name) or ".." in name:
            raise OutputError(
                f"{field} = {name!r} cannot be a file name: use 1-100 letters, digits, "
                f"'_', '-' or '.', starting with a letter or digit (no '/', no '..')"
            )
        key = name.casefold()
        if key in seen:
            raise OutputError(
                f"{field} = {name!r} is a duplicate of {seen[key]!r}: names must be unique "
                f"(case-insensitively), each names its own output file"
            )
        seen[key] = name
        out.append(name)
    return out


def check_output_dir(out: str | Path) -> Path:
    """Check an output folder before any work: missing, empty, or an earlier run's folder.

    Returns the absolute path. Creates nothing.

    Raises
    ------
    OutputError
        The path is an existing file, a folder holding files nanostage did not write, or
        its nearest existing parent is not a writable folder.
    """
    p = Path(out).expanduser().absolute()
    if p.exists() or p.is_symlink():
        if not p.is_dir():
            raise OutputError(f"--out {str(out)!r} is an existing file, not a folder")
        entries = list(p.iterdir())
        if entries and not (p / RUN_MANIFEST).is_file():
            raise OutputError(
                f"--out {str(out)!r} is a folder of other files ({len(entries)} entries, no "
                f"{RUN_MANIFEST}): give a new or empty folder, or one an earlier nanostage "
                f"run wrote"
            )
    parent = p.parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
        raise OutputError(f"--out {str(out)!r}: cannot write into {str(parent)!r}")
    return p


def _files(root: Path) -> list[str]:
    return sorted(str(f.relative_to(root)) for f in root.rglob("*") if f.is_file())


def _fresh_dir(parent: Path, prefix: str) -> Path:
    """A new folder ``parent/prefix<random>`` with the permissions of a plain ``mkdir`` (the
    umask applies; :func:`tempfile.mkdtemp` would make it private to the user)."""
    for _ in range(100):
        p = parent / f"{prefix}{secrets.token_hex(4)}"
        try:
            p.mkdir()
        except FileExistsError:
            continue
        return p
    raise OutputError(f"cannot create a temporary folder {prefix}* in {str(parent)!r}")


@contextmanager
def staged_output(out: str | Path, command: str) -> Iterator[Path]:
    """Write a run's output folder whole or not at all.

    Yields a temporary folder beside ``out`` to write into. On normal exit a manifest
    (:data:`RUN_MANIFEST`: the command and the files) is written last and the folder
    replaces ``out`` (an earlier run's folder there is removed); on any exception,
    ``KeyboardInterrupt`` included, the temporary folder is removed and ``out`` is left as
    it was.

    Raises
    ------
    OutputError
        From :func:`check_output_dir`, before the body runs.
    """
    target = check_output_dir(out)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = _fresh_dir(target.parent, f".{target.name}.partial-")
    try:
        yield tmp
        write_json({"command": command, "files": _files(tmp)}, tmp / RUN_MANIFEST)
        # The folder may have been filled by someone else meanwhile: check again.
        check_output_dir(target)
        old: Path | None = None
        try:
            if target.exists():
                old = Path(tempfile.mkdtemp(prefix=f".{target.name}.old-", dir=target.parent))
                os.replace(target, old / "previous")
            os.replace(tmp, target)
        except BaseException:
            # A signal (raised as an exception) or an error between the two renames: the
            # previous folder goes back into place.
            if old is not None:
                if (old / "previous").exists() and not target.exists():
                    os.replace(old / "previous", target)
                shutil.rmtree(old, ignore_errors=True)
            raise
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


class ProgressBar:
    """A one-line text progress bar on a stream (no dependency)."""

    def __init__(
        self, total: int, stream: TextIO | None, label: str, *, unit: str = "trials"
    ) -> None:
        self.total = total
        self.stream = stream
        self.label = label
        self.unit = unit
        self.t0 = time.perf_counter()
        self.last = -1
        self.last_write = -math.inf

    def update(self, done: int, *, final: bool = False, suffix: str = "") -> None:
        if self.stream is None or (done == self.last and not final):
            return
        now = time.perf_counter()
        if not final and now - self.last_write < PROGRESS_REFRESH_S:
            return
        self.last = done
        self.last_write = now
        frac = min(1.0, done / self.total) if self.total else 1.0
        filled = round(frac * _BAR_WIDTH)
        elapsed = time.perf_counter() - self.t0
        rate = done / elapsed if elapsed > 0 else 0.0
        self.stream.write(
            f"\r{self.label} [{'#' * filled}{'.' * (_BAR_WIDTH - filled)}] "
            f"{done}/{self.total} {self.unit}, {elapsed:.1f} s, {rate:.1f} {self.unit}/s{suffix}"
            + ("\n" if final else "")
        )
        self.stream.flush()
