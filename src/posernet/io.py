"""Atomic file output: write to a temporary file beside the target, then rename over it.

A reader therefore sees either the old file or the complete new one, never a half-written file,
even when the writer is interrupted.

Permissions: the temporary file is created with mode ``0o666`` and the kernel applies the
process umask (and any default ACL of the folder), exactly as for ``open(path, "w")``. So an
output written here gets the permissions of any other new file of the process (``0644`` under
the usual umask ``022``, ``0664`` under ``002``), not the ``0600`` of :func:`tempfile.mkstemp`.
A file that is replaced gets those permissions too (its old mode is not carried over).
Every output of posernet goes through this module; :func:`writable_dir` and
:func:`writable_file` check, before any work, that an output can be written (creating nothing).
"""

from __future__ import annotations

import json
import os
import secrets
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from .options import ConfigValueError

__all__ = ["atomic_path", "atomic_write_bytes", "atomic_write_json", "atomic_write_text",
           "writable_dir", "writable_file"]

_FLAGS = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0) \
    | getattr(os, "O_BINARY", 0)


def _create_temp(folder: Path, name: str, suffix: str) -> Path:
    """A new empty file ``folder/.name.<random><suffix>``, created with mode 0o666 & ~umask."""
    for _ in range(100):
        tmp = folder / f".{name}.{secrets.token_hex(6)}{suffix}"
        try:
            fd = os.open(tmp, _FLAGS, 0o666)
        except FileExistsError:
            continue
        os.close(fd)
        return tmp
    raise FileExistsError(f"could not create a temporary file for {folder / name}")


@contextmanager
def atomic_path(path: str | os.PathLike[str], suffix: str = ".tmp") -> Iterator[Path]:
    """Yield a temporary path in the target's directory; rename it onto ``path`` on success.

    The temporary file exists (empty) when yielded; write to it by name. ``suffix`` is its
    extension (e.g. ``".png"`` for writers that pick the format from the name). On an
    exception the temporary file is removed and ``path`` is left untouched. The written file
    has the process umask's permissions (see the module docstring).
    """
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp_path = _create_temp(target.parent, target.name, suffix)
    try:
        yield tmp_path
        os.replace(tmp_path, target)
    except BaseException:
        tmp_path.unlink(missing_ok=True)
        raise


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically; returns the path."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def atomic_write_text(path: str | os.PathLike[str], text: str) -> Path:
    """Write ``text`` to ``path`` atomically (UTF-8); returns the path."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def atomic_write_json(path: str | os.PathLike[str], obj: Any, indent: int | None = 1) -> Path:
    """Serialise ``obj`` as JSON to ``path`` atomically (NaN/inf are refused)."""
    with atomic_path(path) as tmp, open(tmp, "w", encoding="utf-8") as fh:
        json.dump(obj, fh, indent=indent, allow_nan=False)
    return Path(path)


# --------------------------------------------------------------------------- output probing


def _nearest_existing(p: Path) -> Path:
    q = p
    while not os.path.lexists(q) and q.parent != q:
        q = q.parent
    return q


def writable_dir(folder: Any, key: str = "out_dir") -> Path:
    """Check that ``folder`` is (or can be made) a folder that takes files; creates nothing.

    The nearest existing folder on its path gets a probe file, removed at once. Raises
    :class:`~posernet.options.ConfigValueError` naming ``key`` and the path as given.
    """
    p = Path(str(folder))
    q = _nearest_existing(p.absolute())
    where = "it" if q == p.absolute() else str(q)
    if not q.is_dir():
        raise ConfigValueError(f"{key}: {str(folder)!r} is not a writable folder "
                               f"({where} is not a folder)")
    try:
        fd, probe = tempfile.mkstemp(prefix=".posernet-write-test-", dir=q)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise ConfigValueError(f"{key}: {str(folder)!r} is not a writable folder "
                               f"(cannot write in {q}: {exc.strerror})") from None
    return p


def writable_file(file: Any, key: str = "output") -> Path:
    """Check that file ``file`` can be written (created or replaced); creates nothing."""
    p = Path(str(file))
    if p.is_dir():
        raise ConfigValueError(f"{key}: {str(file)!r} is not a writable file (it is a folder)")
    try:
        writable_dir(p.parent, key)
    except ConfigValueError as exc:
        detail = str(exc).split(" is not a writable folder ", 1)[-1]
        raise ConfigValueError(f"{key}: {str(file)!r} is not a writable file {detail}") from None
    return p
