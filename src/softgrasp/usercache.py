"""softgrasp's cache folder: results that are slow to make and the same every time.

A repeated plan of a built-in object does not mesh it again, a packaged or user hand is not
read through the URDF library again, and an object planned again (another hand, other
fingertips, another safety factor) does not settle on the table again: these are kept here, one
file per entry, named by the
SHA-256 of everything the entry depends on (its parameters, the versions of the libraries that
made it and the sources of the softgrasp modules that made it), so an entry is never stale, only
unused. The folder is ``$XDG_CACHE_HOME/softgrasp`` (the XDG convention), else
``~/.cache/softgrasp``; deleting it at any time is safe.

Entries are NumPy ``.npz`` files (no pickles: nothing is executed on load) written atomically.
The cache is an optimisation only: a folder that cannot be written, or a damaged entry, is
skipped and the result is made again. An entry is made under its lock (:func:`making`): a
second process that needs it meanwhile waits for it instead of making it too (a first plan's
two compiling processes, the workers of a sweep).
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import tempfile
import zipfile
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "cache_dir",
    "entry_key",
    "load",
    "making",
    "package_digest",
    "source_digest",
    "store",
    "value_digest",
]


def cache_dir() -> Path:
    """The cache folder (module docstring); not created here."""
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "softgrasp"


def source_digest(*modules: str) -> str:
    """SHA-256 of the source files of softgrasp's ``modules`` (dotted names), read from the
    package folder without importing them."""
    root = Path(__file__).resolve().parent
    h = hashlib.sha256()
    for name in modules:
        path = root.joinpath(*name.split(".")[1:]).with_suffix(".py")
        h.update(name.encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()


def package_digest(*packages: str) -> str:
    """SHA-256 of every source file of softgrasp's ``packages`` (dotted names of subpackages, or
    of modules), in a fixed order, read without importing them."""
    root = Path(__file__).resolve().parent
    h = hashlib.sha256()
    for name in packages:
        base = root.joinpath(*name.split(".")[1:])
        files = sorted(base.rglob("*.py")) if base.is_dir() else [base.with_suffix(".py")]
        for path in files:
            h.update(path.relative_to(root).as_posix().encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()


class _Opaque(Exception):
    """A value :func:`value_digest` cannot write down exactly."""


def _feed(h, value: object) -> None:
    if value is None or isinstance(value, (bool, int, float, str, bytes)):
        h.update(type(value).__name__.encode() + b":" + repr(value).encode() + b"\0")
    elif isinstance(value, np.generic):
        _feed(h, value.item())
    elif isinstance(value, np.ndarray):
        if value.dtype.hasobject:
            raise _Opaque(value.dtype)
        a = np.ascontiguousarray(value)
        h.update(f"array:{a.dtype.str}:{a.shape}".encode() + b"\0" + a.tobytes() + b"\0")
    elif isinstance(value, (tuple, list)):
        h.update(f"{type(value).__name__}:{len(value)}".encode() + b"\0")
        for v in value:
            _feed(h, v)
    elif isinstance(value, dict):
        h.update(f"dict:{len(value)}".encode() + b"\0")
        for k in sorted(value, key=repr):
            _feed(h, k)
            _feed(h, value[k])
    elif dataclasses.is_dataclass(value) and not isinstance(value, type):
        h.update(f"{type(value).__module__}.{type(value).__qualname__}".encode() + b"\0")
        for f in dataclasses.fields(value):
            h.update(f.name.encode() + b"=")
            _feed(h, getattr(value, f.name))
    else:
        raise _Opaque(type(value))


def value_digest(value: object) -> str | None:
    """SHA-256 of ``value`` written down exactly: numbers, strings, arrays (dtype, shape and
    bytes), tuples, lists, dicts and dataclasses (their type and every field), recursively; None
    when it holds anything else (an object whose state this cannot see: no entry is kept for it)."""
    h = hashlib.sha256()
    try:
        _feed(h, value)
    except _Opaque:
        return None
    return h.hexdigest()


def entry_key(*parts: object) -> str:
    """The name of an entry: SHA-256 over the ``repr`` of each part (numbers, strings, bytes)."""
    h = hashlib.sha256()
    for p in parts:
        h.update(p if isinstance(p, bytes) else repr(p).encode())
        h.update(b"\0")
    return h.hexdigest()


def _path(kind: str, key: str) -> Path:
    return cache_dir() / kind / f"{key}.npz"


def load(kind: str, key: str) -> dict[str, NDArray] | None:
    """The arrays stored under ``kind``/``key``, or None when there is no readable entry."""
    path = _path(kind, key)
    try:
        with np.load(path, allow_pickle=False) as data:
            return {name: data[name] for name in data.files}
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile):
        return None


@contextmanager
def making(kind: str, key: str) -> Iterator[None]:
    """Hold the lock of entry ``kind``/``key`` while it is made: another process making the same
    entry waits here until this one is done, then finds it with :func:`load`. Use::

        kept = load(kind, key)
        if kept is None:
            with making(kind, key):
                kept = load(kind, key)  # made meanwhile by another process
                if kept is None:
                    ...  # make it and store() it

    Without a lock (a folder that cannot be written, a system without ``fcntl``) it only runs
    the block."""
    try:
        import fcntl

        path = _path(kind, key)
        path.parent.mkdir(parents=True, exist_ok=True)
        lock = open(f"{path}.lock", "a")  # noqa: SIM115 - held across the yield
    except (ImportError, OSError):
        yield
        return
    with lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX)
        except OSError:
            pass
        yield


def store(kind: str, key: str, arrays: Mapping[str, NDArray | str | float]) -> None:
    """Keep ``arrays`` under ``kind``/``key`` (atomically); a failure to write is ignored."""
    path = _path(kind, key)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".entry.", suffix=".npz", dir=path.parent)
        try:
            with os.fdopen(fd, "wb") as f:
                np.savez(f, **{k: np.asarray(v) for k, v in arrays.items()})
            os.replace(tmp, path)
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
    except OSError:
        pass
