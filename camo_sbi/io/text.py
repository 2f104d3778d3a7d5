"""Reading a text file a person or another program wrote: one clear error for what it is not."""

from __future__ import annotations

from pathlib import Path

__all__ = ["read_text"]


def read_text(path: Path, what: str) -> str:
    """The UTF-8 text of ``path`` (a BOM accepted); one ValueError naming the file for an unreadable,
    binary (NUL bytes) or non-UTF-8 file, saying it was expected to be ``what``."""
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise ValueError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    if b"\0" in raw[:65536]:
        raise ValueError(f"{path}: is a binary file, not {what} (it holds NUL bytes)")
    try:
        return raw.decode("utf-8-sig")  # a UTF-8 BOM (every Excel export) is accepted
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: is not UTF-8 text (byte 0x{raw[exc.start]:02x} at offset {exc.start}): "
                         f"expected {what}") from None
