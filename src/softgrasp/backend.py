"""Which implementation evaluates the body's forces: compiled Numba kernels or the NumPy reference.

The NumPy functions of :mod:`softgrasp.physics.forces` are the reference; :mod:`softgrasp.physics.forces_compiled`
holds compiled (Numba) kernels with the same signatures and results (to round-off, tested to
1e-8 relative). :class:`softgrasp.physics.body.Body` asks :func:`compiled` on every call and uses the
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
    """Whether the compiled (Numba) kernels are in use: the ``numba`` backend, except in a
    process forked from one whose Numba threads were GNU OpenMP's (:func:`forked`), where any
    parallel kernel would terminate it: there the NumPy kernels, SciPy's and pyamg's run."""
    return get_backend() == "numba" and not _FORKED


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


#: The shared library of Intel TBB that Numba's ``tbb`` threading layer links against.
TBB_LIBRARY = "libtbb.so.12"
#: The oldest TBB Numba's layer accepts (``TBB_runtime_interface_version``: 2021 update 6).
TBB_MIN_INTERFACE = 12060


def _tbb_paths() -> Iterator[str]:
    """Where to look for :data:`TBB_LIBRARY`: the loader's own search (a conda or system TBB),
    then where pip's ``tbb`` distribution put it (the environment's ``lib`` directory, which is
    not on the loader's path), its record of its files read only when that guess fails (~40 ms)."""
    import sys

    yield TBB_LIBRARY
    yield os.path.join(sys.prefix, "lib", TBB_LIBRARY)
    try:
        from importlib import metadata

        dist = metadata.distribution("tbb")
        files = dist.files or []
    except Exception:  # not installed, or no record of its files
        return
    for f in files:
        if f.name == TBB_LIBRARY:
            yield str(dist.locate_file(f))


def _tbb_usable(lib: object) -> bool:
    """Whether the loaded TBB ``lib`` is one Numba's layer accepts (else Numba would warn and
    fall back to OpenMP; a warning filter set to error would make that an exception)."""
    import ctypes

    try:
        version = lib.TBB_runtime_interface_version  # type: ignore[attr-defined]
    except AttributeError:
        return False
    version.argtypes = []
    version.restype = ctypes.c_int
    return int(version()) >= TBB_MIN_INTERFACE


def _load_tbb() -> str | None:
    """Make Intel TBB loadable for Numba's threading layer; what was loaded (a name or a path),
    or None.

    Numba tries its threading layers in the order ``tbb``, ``omp``, ``workqueue``; its ``tbb``
    layer needs :data:`TBB_LIBRARY`, which pip installs into the environment's ``lib`` directory
    where the loader does not look, so Numba used to settle for GNU OpenMP. That layer does not
    survive ``fork()``: a parallel kernel run in the child of a process that had started its
    threads terminates the child ("fork() called from a process already using GNU OpenMP"), so a
    script that plans and then forks workers lost them. TBB's layer is fork-safe and thread-safe
    and as fast here (the 27 749-node plan 9.7 s on either, alternating). Loading the library
    once, globally, lets Numba's own choice (or ``NUMBA_THREADING_LAYER=tbb``, ``safe``...) find
    it; a TBB already in the process is used as it is, one too old for Numba is unloaded again.
    Linux only (elsewhere the loader finds pip's TBB, or Numba's other layers are fork-safe)."""
    import sys

    if not sys.platform.startswith("linux"):
        return None
    import ctypes

    try:  # already loaded (by MKL, or from the loader's path): no second copy
        if _tbb_usable(ctypes.CDLL(TBB_LIBRARY, mode=ctypes.RTLD_GLOBAL | os.RTLD_NOLOAD)):
            return TBB_LIBRARY
    except OSError:
        pass
    for path in _tbb_paths():
        if path != TBB_LIBRARY and not os.path.exists(path):
            continue
        try:
            lib = ctypes.CDLL(path, mode=ctypes.RTLD_GLOBAL)
        except OSError:
            continue
        if _tbb_usable(lib):
            return path
        import _ctypes

        _ctypes.dlclose(lib._handle)  # too old: Numba would warn and take OpenMP anyway
    return None


_load_tbb()  # before any parallel kernel starts Numba's threads (all of them live in this package)

_FORKED = False


def _threads_lost() -> bool:
    """Whether Numba's parallel threads, started before a fork, are unusable in the child: only
    the GNU OpenMP layer (``omp`` on Linux) is not fork-safe; no threads started means nothing
    lost."""
    import sys

    numba = sys.modules.get("numba")
    if numba is None or not sys.platform.startswith("linux"):
        return False
    try:
        layer = numba.threading_layer()
    except ValueError:  # no parallel kernel has run: the child starts its own threads
        return False
    return layer == "omp"


def _mark_forked() -> None:
    global _FORKED
    _FORKED = _threads_lost()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_mark_forked)


def forked() -> bool:
    """Whether this process is a fork of one whose Numba threads do not survive the fork. With
    GNU OpenMP as Numba's threading layer (TBB not installed, or ``NUMBA_THREADING_LAYER=omp``) a
    parallel kernel run in the child of a process that had started those threads terminates it
    ("fork() called from a process already using GNU OpenMP"); there :func:`compiled` is false
    and the NumPy kernels run (slower, the same results to round-off). With TBB (the default
    where it is installed) this is False. (TBB's layer resets itself in the child when the fork
    comes from the thread that started Numba's threads; from another thread Numba warns that
    the child's TBB may be in an invalid state.)"""
    return _FORKED
