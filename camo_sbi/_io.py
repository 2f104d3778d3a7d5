"""Atomic file writes (a reader sees the old file or the new one, never a partial one) and
private directories (`check_private_dir`, `make_private_dir`: where code caches may live)."""

from __future__ import annotations

import os
import stat
import tempfile
from pathlib import Path

__all__ = ["atomic_write_bytes", "atomic_write_text", "check_private_dir", "make_private_dir"]


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (temp file in the same folder, fsync, replace)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        umask = os.umask(0)
        os.umask(umask)
        os.fchmod(fd, 0o666 & ~umask)  # mkstemp creates 0600; give the file normal permissions
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except OSError as exc:  # a full disk: the error names the file being written (one CLI line)
        Path(tmp).unlink(missing_ok=True)
        if exc.filename is None and exc.errno is not None:
            raise OSError(exc.errno, exc.strerror, str(path)) from exc
        raise
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    return atomic_write_bytes(path, text.encode("utf-8"))


def _current_uid() -> int:
    return os.getuid()


def check_private_dir(path: str | os.PathLike, *, subdirs=("__pycache__",)) -> str | None:
    """Why ``path`` must not hold cached code, or None when it is a private directory of this user.

    A cache that is unpickled must be a real directory (not a symbolic link), owned by the
    current user and writable by no one else (group/other write bits clear); so must each of
    ``subdirs`` that exists.
    """
    root = Path(path)
    for d in (root, *(root / s for s in subdirs)):
        try:
            st = os.lstat(d)
        except FileNotFoundError:
            if d == root:
                return "does not exist"
            continue  # created later inside the checked directory
        except OSError as exc:
            return f"cannot be inspected ({exc.strerror or exc})"
        where = "" if d == root else f" (its {d.name})"
        if stat.S_ISLNK(st.st_mode):
            return f"is a symbolic link{where}"
        if not stat.S_ISDIR(st.st_mode):
            return f"is not a directory{where}"
        if st.st_uid != _current_uid():
            return f"is owned by uid {st.st_uid}, not by this user (uid {_current_uid()}){where}"
        if st.st_mode & 0o022:
            return f"is writable by group or others (mode {stat.S_IMODE(st.st_mode):o}){where}"
    return None


def make_private_dir(path: str | os.PathLike, *, subdirs=("__pycache__",)) -> str | None:
    """Create ``path`` with mode 0700 if missing (parents as usual); why it is unusable, or None.

    An existing directory is not changed, only checked (`check_private_dir`).
    """
    d = Path(path)
    if not os.path.lexists(d):
        try:
            d.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            return f"cannot be created ({exc.strerror or exc})"
        try:
            os.mkdir(d, 0o700)
        except FileExistsError:
            pass  # another process created it meanwhile: checked below like any existing directory
        except OSError as exc:
            return f"cannot be created ({exc.strerror or exc})"
        else:
            if stat.S_IMODE(os.lstat(d).st_mode) & 0o077:
                return f"was created with mode {stat.S_IMODE(os.lstat(d).st_mode):o}, not 700"
    return check_private_dir(d, subdirs=subdirs)
