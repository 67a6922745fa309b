"""What every reader of a CSV text file shares: opening it (UTF-8, an optional BOM),
skipping blank and ``#`` comment rows, the header row, rows wider than the header, and where
a file stops being UTF-8 (for an error that names the byte offset)."""

from __future__ import annotations

import codecs
from collections.abc import Sequence
from pathlib import Path
from typing import IO, Any

__all__ = ["Utf8Error", "find_utf8_error", "open_csv", "read_header", "skip_row", "too_wide"]


def open_csv(path: Path) -> IO[str]:
    """``path`` opened for :func:`csv.reader`: UTF-8 text, a leading BOM dropped."""
    return path.open(newline="", encoding="utf-8-sig")


def skip_row(row: Sequence[str]) -> bool:
    """A blank row or a comment (first cell starting with ``#``)."""
    return not any(c.strip() for c in row) or row[0].lstrip().startswith("#")


def read_header(reader: Any) -> tuple[list[str] | None, int]:
    """The first row of a :func:`csv.reader` that :func:`skip_row` keeps, its cells stripped,
    and its 1-based line; ``(None, 1)`` when every row is skipped."""
    for row in reader:
        if not skip_row(row):
            return [c.strip() for c in row], reader.line_num
    return None, 1


def too_wide(row: Sequence[str], width: int) -> bool:
    """``row`` has a non-blank field beyond the header's ``width`` fields."""
    return len(row) > width and any(c.strip() for c in row[width:])


class Utf8Error(Exception):
    """Where a file stops being UTF-8: 0-based byte offset, 1-based line, the byte."""

    def __init__(self, offset: int, line: int, byte: int, reason: str) -> None:
        super().__init__(offset, line, byte, reason)
        self.offset, self.line, self.byte, self.reason = offset, line, byte, reason


def find_utf8_error(path: Path, chunk_bytes: int = 1 << 20) -> Utf8Error | None:
    """The first byte of ``path`` that is not UTF-8, read in chunks (no whole-file copy)."""
    decoder = codecs.getincrementaldecoder("utf-8")()
    pos = 0
    lines = 0
    with path.open("rb") as fh:
        while True:
            chunk = fh.read(chunk_bytes)
            pending = decoder.getstate()[0]
            try:
                decoder.decode(chunk, final=not chunk)
            except UnicodeDecodeError as exc:
                data = pending + chunk
                offset = pos - len(pending) + exc.start
                line = lines + data[: exc.start].count(b"\n") + 1
                return Utf8Error(offset, line, data[exc.start], exc.reason)
            if not chunk:
                return None
            pos += len(chunk)
            lines += chunk.count(b"\n")
