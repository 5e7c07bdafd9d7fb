"""Numba's threads and ``fork()``: loading Intel TBB for Numba's threading layer, and telling a
forked child whose Numba threads were lost.

softgrasp's force, contact and solver kernels are compiled with Numba (a hard dependency); some
run on Numba's threads. GNU OpenMP's threading layer does not survive ``fork()``: a parallel
kernel run in the child of a process that had started its threads terminates the child. This
module makes TBB's fork-safe layer available to Numba (:func:`_load_tbb`, at import) and records
whether this process is a child whose threads were lost (:func:`forked`); there the kernels that
would run on Numba's threads run their serial form instead (:func:`compiled` is false for the
solver code that then takes SciPy's and pyamg's routines).
"""

from __future__ import annotations

import os
from collections.abc import Iterator

__all__ = ["compiled", "forked", "forks_lose_threads"]


def compiled() -> bool:
    """Whether Numba's parallel kernels may run in this process: false only in a process forked
    from one whose Numba threads were GNU OpenMP's (:func:`forked`), where any parallel kernel
    would terminate it."""
    return not _FORKED


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
    and as fast. Loading the library
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


def forks_lose_threads() -> bool:
    """Whether a child forked from this process now would lose Numba's threads
    (:func:`_threads_lost`: GNU OpenMP's layer has started them)."""
    return _threads_lost()


def _mark_forked() -> None:
    global _FORKED
    _FORKED = _threads_lost()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_mark_forked)


def forked() -> bool:
    """Whether this process is a fork of one whose Numba threads do not survive the fork. With
    GNU OpenMP as Numba's threading layer (TBB not installed, or ``NUMBA_THREADING_LAYER=omp``) a
    parallel kernel run in the child of a process that had started those threads terminates it
    ("fork() called from a process already using GNU OpenMP"); there the body's force and
    Jacobian sums run their groups one after another on the calling thread (the same sums), and
    :func:`compiled` is false for the solver code (SciPy's and pyamg's routines). With TBB (the default
    where it is installed) this is False. (TBB's layer resets itself in the child when the fork
    comes from the thread that started Numba's threads; from another thread Numba warns that
    the child's TBB may be in an invalid state.)"""
    return _FORKED
