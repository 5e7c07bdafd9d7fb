"""Which implementation evaluates the body's forces: compiled Numba kernels or the NumPy reference.

The NumPy functions of :mod:`softgrasp.forces` are the reference; :mod:`softgrasp.kernels.elastic`
holds compiled (Numba) kernels with the same signatures and results (to round-off, tested to
1e-8 relative). :class:`softgrasp.body.Body` asks :func:`compiled` on every call and uses the
compiled kernels when it says so.

Choosing the backend
--------------------
* default: ``"numba"`` when Numba can be imported, else ``"numpy"`` (silently when Numba is not
  installed, with a warning when it is installed but fails to import);
* the environment variable ``SOFTGRASP_KERNELS=numba|numpy`` (read once, at the first query);
  asking for ``numba`` when it cannot be used falls back to ``numpy`` with a warning;
* :func:`set_backend` or the context manager :func:`use_backend` at run time (these raise
  :class:`~softgrasp.errors.ConfigError` for an unknown name or a missing Numba).

Numba itself is imported lazily, at the first compiled call, so importing softgrasp stays cheap;
compiled code is cached on disk (``cache=True``), so only the very first run pays the compilation.
"""

from __future__ import annotations

import functools
import importlib.util
import os
import warnings
from collections.abc import Iterator
from contextlib import contextmanager

from softgrasp.errors import ConfigError

__all__ = [
    "BACKENDS",
    "ENV_VAR",
    "available",
    "compiled",
    "forked",
    "get_backend",
    "set_backend",
    "use_backend",
]

#: Backend names.
BACKENDS = ("numba", "numpy")
#: Environment variable that selects the default backend.
ENV_VAR = "SOFTGRASP_KERNELS"

_backend: str | None = None  # resolved lazily by get_backend()


_NOT_INSTALLED = "Numba is not installed (pip install numba)"


@functools.cache
def _numba_error() -> str | None:
    """Why Numba cannot be used, or None when it imports."""
    if importlib.util.find_spec("numba") is None:
        return _NOT_INSTALLED
    try:
        import numba  # noqa: F401
    except Exception as exc:  # a broken installation, e.g. built for another NumPy
        return f"Numba is installed but cannot be imported ({type(exc).__name__}: {exc})"
    return None


def available() -> tuple[str, ...]:
    """Backends usable in this environment (``numpy`` always; ``numba`` when it imports)."""
    return BACKENDS if _numba_error() is None else ("numpy",)


def _default() -> str:
    requested = os.environ.get(ENV_VAR, "").strip().lower()
    if requested and requested not in BACKENDS:
        warnings.warn(
            f"{ENV_VAR}={requested!r} is not a kernel backend ({', '.join(BACKENDS)}); using the default",
            stacklevel=3,
        )
        requested = ""
    if requested == "numpy":
        return "numpy"
    if "numba" in available():
        return "numba"
    error = _numba_error()
    if requested == "numba" or error != _NOT_INSTALLED:  # asked for, or installed but broken
        warnings.warn(f"{error}; using the NumPy kernels (several times slower)", stacklevel=3)
    return "numpy"


def get_backend() -> str:
    """The current backend name, ``"numba"`` or ``"numpy"``."""
    global _backend
    if _backend is None:
        _backend = _default()
    return _backend


def compiled() -> bool:
    """Whether the compiled (Numba) kernels are in use."""
    return get_backend() == "numba"


def set_backend(name: str) -> None:
    """Select the kernels: ``"numba"`` (compiled) or ``"numpy"`` (reference).

    Raises
    ------
    ConfigError
        Unknown name, or ``"numba"`` without Numba installed.
    """
    global _backend
    key = str(name).strip().lower()
    if key not in BACKENDS:
        raise ConfigError(f"unknown kernel backend {name!r}; choose one of {', '.join(BACKENDS)}")
    if key not in available():
        raise ConfigError(f"the numba kernel backend is unavailable: {_numba_error()}")
    _backend = key


@contextmanager
def use_backend(name: str) -> Iterator[None]:
    """Context manager: run the block with backend ``name``, then restore the previous one."""
    previous = get_backend()
    set_backend(name)
    try:
        yield
    finally:
        set_backend(previous)


_FORKED = False


def _mark_forked() -> None:
    global _FORKED
    _FORKED = True


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_mark_forked)


def forked() -> bool:
    """Whether this process is a fork of one that imported softgrasp. Numba's OpenMP threads do
    not survive a fork: a parallel kernel run in the child of a process that had started them
    terminates it ("fork() called from a process already using GNU OpenMP"), so work that has a
    serial equivalent takes it there."""
    return _FORKED
