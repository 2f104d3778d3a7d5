"""Reading a user's text, JSON and TOML files: the one place, so that every reader fails alike.

Every failure is a ``ValueError`` whose message starts with the caller's ``label`` (the flag
and the file, e.g. ``"--limits: limits.json"``) and fits on one line: a file that cannot be
read, one larger than ``max_bytes``, one that is not UTF-8, invalid JSON/TOML, and data nested
deeper than `MAX_DEPTH` levels (Python's parsers recurse: 100,000 ``[`` would otherwise end in a
``RecursionError`` traceback). A leading UTF-8 byte-order mark (Excel, Notepad) is accepted.
"""

from __future__ import annotations

import json
import os
import tomllib
from pathlib import Path
from typing import Any

__all__ = ["MAX_DEPTH", "MAX_TEXT_BYTES", "parse_json", "parse_toml", "read_json", "read_text", "read_toml"]

MAX_TEXT_BYTES = 16 * 2**20
"""A settings, mapping, frame, limits or study file is kilobytes; 16 MiB is far beyond any of them."""

MAX_DEPTH = 64
"""Nesting levels a JSON/TOML file may use (the toolkit's own files use at most 4)."""


def _depth_exceeds(data: Any, limit: int) -> bool:
    """Whether ``data`` (parsed JSON/TOML) nests containers deeper than ``limit`` (no recursion)."""
    stack = [(data, 1)]
    while stack:
        x, d = stack.pop()
        if isinstance(x, dict):
            items = x.values()
        elif isinstance(x, list):
            items = x
        else:
            continue
        if d > limit:
            return True
        stack.extend((v, d + 1) for v in items if isinstance(v, (dict, list)))
    return False


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())[:200]


def read_text(path, label: str | None = None, *, max_bytes: int = MAX_TEXT_BYTES) -> str:
    """The UTF-8 text of ``path`` (a leading byte-order mark removed); ValueError starting with
    ``label`` (default: the path) when it cannot be read, is over ``max_bytes`` or is not UTF-8."""
    path = Path(path)
    label = str(path) if label is None else label
    try:
        with open(path, "rb") as fh:
            size = os.fstat(fh.fileno()).st_size
            if size > max_bytes:
                raise ValueError(f"{label}: {size:,} bytes, more than the {max_bytes:,} such a file may hold")
            raw = fh.read(max_bytes + 1)
    except OSError as exc:
        raise ValueError(f"{label}: cannot read ({exc.strerror or exc})") from None
    if len(raw) > max_bytes:  # a pipe or a special file that reports no size
        raise ValueError(f"{label}: more than the {max_bytes:,} bytes such a file may hold")
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ValueError(f"{label}: not a UTF-8 text file (byte {exc.start} is {raw[exc.start:exc.start + 1]!r})"
                         ) from None


def _check_depth(data: Any, label: str) -> Any:
    if _depth_exceeds(data, MAX_DEPTH):
        raise ValueError(f"{label}: nested more than {MAX_DEPTH} levels deep")
    return data


def parse_json(text: str, label: str) -> Any:
    """``json.loads(text)``; ValueError starting with ``label`` on invalid or too deeply nested JSON."""
    try:
        data = json.loads(text)
    except RecursionError:
        raise ValueError(f"{label}: invalid JSON (nested more than {MAX_DEPTH} levels deep)") from None
    except ValueError as exc:
        raise ValueError(f"{label}: invalid JSON ({_one_line(exc)})") from None
    return _check_depth(data, label)


def parse_toml(text: str, label: str) -> dict:
    """``tomllib.loads(text)``; ValueError starting with ``label`` on invalid or too deeply nested TOML."""
    try:
        data = tomllib.loads(text)
    except RecursionError:
        raise ValueError(f"{label}: invalid TOML (nested more than {MAX_DEPTH} levels deep)") from None
    except ValueError as exc:  # tomllib.TOMLDecodeError
        raise ValueError(f"{label}: invalid TOML ({_one_line(exc)})") from None
    return _check_depth(data, label)


def read_json(path, label: str | None = None, *, max_bytes: int = MAX_TEXT_BYTES) -> Any:
    """The parsed JSON file ``path`` (see `read_text` and `parse_json`)."""
    label = str(path) if label is None else label
    return parse_json(read_text(path, label, max_bytes=max_bytes), label)


def read_toml(path, label: str | None = None, *, max_bytes: int = MAX_TEXT_BYTES) -> dict:
    """The parsed TOML file ``path`` (see `read_text` and `parse_toml`)."""
    label = str(path) if label is None else label
    return parse_toml(read_text(path, label, max_bytes=max_bytes), label)
