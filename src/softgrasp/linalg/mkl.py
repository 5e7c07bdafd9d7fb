"""Intel oneMKL as softgrasp calls it: the library, its thread count, and the PARDISO call.

The library is the one the ``mkl`` wheel installs (``libmkl_rt``, found in the environment's
``lib`` directory or through the wheel's file list, else by the system's library search);
:func:`available` says whether it loaded, and :mod:`softgrasp.linalg.solve` falls back to
SciPy's sparse LU and multigrid-preconditioned CG where it did not. MKL runs on Intel's OpenMP
runtime, whatever OpenMP another library loaded first.

Every PARDISO call is made through :func:`call` holding one lock, with the thread count of the
handle's analysis (PARDISO sizes its work per thread when it analyses a pattern; a factorisation
run with another count crashes MKL). The count itself is :mod:`softgrasp.linalg.threads`'s.
"""

from __future__ import annotations

import contextlib
import ctypes
import glob
import os
import sys
import threading
from collections.abc import Iterator
from ctypes.util import find_library
from functools import cache

import numpy as np
from numpy.typing import NDArray

from softgrasp.linalg.threads import choose_threads

__all__ = ["PardisoError", "available", "blas_one_thread", "call", "library", "release_later"]

#: MKL's code for its Intel OpenMP threading layer (``MKL_Set_Threading_Layer``).
MKL_THREADING_INTEL = 0
#: MKL's conditional numerical reproducibility on the code branch it picks (``MKL_CBWR_Set``).
MKL_CBWR_AUTO = 2

_ERRORS = {
    -1: "input inconsistent",
    -2: "not enough memory",
    -3: "reordering problem",
    -4: "zero pivot, numerical factorisation or iterative refinement problem",
    -5: "unclassified (internal) error",
    -6: "reordering failed",
    -7: "diagonal matrix is singular",
    -8: "32-bit integer overflow problem",
    -9: "not enough memory for out-of-core solver",
    -10: "error opening out-of-core files",
    -11: "read/write error with out-of-core files",
}


class PardisoError(RuntimeError):
    """PARDISO reported an error (the message gives its code and meaning; ``code``: PARDISO's
    error code, None where PARDISO was not called)."""

    def __init__(self, message: str, code: int | None = None) -> None:
        super().__init__(message)
        self.code = code

    @classmethod
    def of(cls, phase: int, code: int) -> PardisoError:
        """The error of a call of ``phase`` that returned ``code``."""
        return cls(f"PARDISO phase {phase} failed: {_ERRORS.get(code, 'error')} ({code})", code)


_INT = ctypes.POINTER(ctypes.c_int32)
_DBL = ctypes.POINTER(ctypes.c_double)

_current_threads = 0
#: Every PARDISO call and thread-count change is made holding this lock, so that calls from
#: several Python threads keep :data:`_current_threads` the count of the call being made.
_LOCK = threading.RLock()
#: Handles of collected factors waiting to be released: (handle, thread count, matrix type, the
#: arrays the handle was made with). A finaliser only appends here (:func:`release_later`); the
#: next PARDISO call releases them.
_RELEASED: list[tuple[NDArray[np.int64], int, int, tuple[NDArray, ...]]] = []


def _candidates() -> Iterator[str]:
    """Where ``libmkl_rt`` may be, each place once, the quickest to look in first (the later
    ones are searched only when the library is not found in the earlier: a wheel's file list
    takes ~25 ms to read, the system's search a process): the environment's own library directory
    (where the ``mkl`` wheel, and conda, put it), the files of the installed ``mkl`` distribution
    (a wheel installed elsewhere), then the system's library search."""
    from importlib.metadata import PackageNotFoundError, distribution

    seen: set[str] = set()

    def fresh(names: list[str]) -> Iterator[str]:
        for name in names:
            if name not in seen:
                seen.add(name)
                yield name

    yield from fresh(sorted(glob.glob(os.path.join(sys.prefix, "lib", "libmkl_rt.so*")), key=len))
    try:
        files = distribution("mkl").files or []
    except PackageNotFoundError:
        files = []
    found = [f for f in files if f.name.startswith("libmkl_rt.so") or f.name == "mkl_rt.dll"]
    yield from fresh(sorted((os.path.normpath(f.locate()) for f in found), key=len))
    system = find_library("mkl_rt")
    yield from fresh([system] if system else [])


@cache
def library() -> ctypes.CDLL | None:
    """MKL's single dynamic library, or None where it is not installed."""
    for name in _candidates():
        try:
            lib = ctypes.CDLL(name)
            lib.pardiso  # noqa: B018 - the symbol must exist
        except (OSError, AttributeError):
            continue
        if not os.environ.get("MKL_THREADING_LAYER"):  # MKL's own setting, where a user made one
            # Intel's OpenMP runtime (shipped with MKL) whatever was loaded before: MKL otherwise
            # takes GNU OpenMP where another library (gmsh) loaded it. Before any other MKL call.
            lib.MKL_Set_Threading_Layer(ctypes.c_int(MKL_THREADING_INTEL))
        # Reproducible from run to run on a fixed thread count (MKL's conditional numerical
        # reproducibility): MKL keeps to the threads it is given, and its code branch is fixed.
        lib.MKL_Set_Dynamic(ctypes.c_int(0))
        lib.MKL_CBWR_Set(ctypes.c_int(MKL_CBWR_AUTO))
        lib.pardiso.restype = None
        return lib
    return None


def available() -> bool:
    """Whether MKL PARDISO could be loaded."""
    return library() is not None


def _use_threads(lib: ctypes.CDLL, n: int) -> None:
    global _current_threads
    if n != _current_threads:
        lib.MKL_Set_Num_Threads(ctypes.c_int(n))
        _current_threads = n


def _arguments(
    pt: NDArray[np.int64],
    mtype: int,
    phase: int,
    data: NDArray,
    indptr: NDArray[np.int32],
    indices: NDArray[np.int32],
    iparm: NDArray[np.int32],
    rhs: NDArray,
    x: NDArray,
    err: ctypes.c_int32,
    perm: NDArray[np.int32] | None = None,
) -> tuple:
    """The sixteen arguments of one ``pardiso`` call (one right-hand side, no messages; ``data``,
    ``rhs`` and ``x`` in float32 where ``iparm[27]`` = 1, else float64)."""
    return (
        pt.ctypes.data_as(ctypes.POINTER(ctypes.c_int64)),
        ctypes.byref(ctypes.c_int32(1)),  # maxfct
        ctypes.byref(ctypes.c_int32(1)),  # mnum
        ctypes.byref(ctypes.c_int32(mtype)),
        ctypes.byref(ctypes.c_int32(phase)),
        ctypes.byref(ctypes.c_int32(indptr.size - 1)),  # n
        data.ctypes.data_as(_DBL),
        indptr.ctypes.data_as(_INT),
        indices.ctypes.data_as(_INT),
        None if perm is None else perm.ctypes.data_as(_INT),  # fill-in reducing ordering
        ctypes.byref(ctypes.c_int32(1)),  # nrhs
        iparm.ctypes.data_as(_INT),
        ctypes.byref(ctypes.c_int32(0)),  # msglvl
        rhs.ctypes.data_as(_DBL),
        x.ctypes.data_as(_DBL),
        ctypes.byref(err),
    )


def _release_pending(lib: ctypes.CDLL) -> None:
    """Release the memory of collected factors (phase -1, each with its own thread count).
    Called holding :data:`_LOCK`, before a call sets its own thread count."""
    while _RELEASED:
        pt, threads, mtype, (data, indptr, indices, iparm) = _RELEASED.pop()
        _use_threads(lib, threads)
        dummy = np.zeros(1)
        lib.pardiso(*_arguments(pt, mtype, -1, data, indptr, indices, iparm, dummy, dummy, ctypes.c_int32(0)))


def call(threads: int, *args: object, **kwargs: object) -> int:
    """One ``pardiso`` call (:func:`_arguments`' arguments) on ``threads`` threads, after the
    releases queued; returns PARDISO's error code (0: success)."""
    lib = library()
    assert lib is not None
    err = ctypes.c_int32(0)
    arguments = _arguments(*args, err=err, **kwargs)  # type: ignore[misc]
    with _LOCK:
        # A collector run in between (any allocation may start one) only queues releases:
        # nothing changes the thread count between the next line and the call.
        _release_pending(lib)
        _use_threads(lib, threads)
        lib.pardiso(*arguments)
    return int(err.value)


def get_diagonal(pt: NDArray[np.int64], df: NDArray, da: NDArray) -> int:
    """``pardiso_getdiag``: the factor's pivots into ``df`` and the matrix's diagonal into ``da``
    (of the handle ``pt``); PARDISO's error code."""
    lib = library()
    assert lib is not None
    err = ctypes.c_int32(0)
    with _LOCK:
        lib.pardiso_getdiag(
            pt.ctypes.data_as(ctypes.POINTER(ctypes.c_int64)),
            df.ctypes.data_as(_DBL),
            da.ctypes.data_as(_DBL),
            ctypes.byref(ctypes.c_int32(1)),
            ctypes.byref(err),
        )
    return int(err.value)


def release_later(pt: NDArray[np.int64], threads: int, mtype: int, arrays: tuple[NDArray, ...]) -> None:
    """Queue a handle's release for the next PARDISO call (a finaliser must not call MKL: it
    runs wherever the collector starts, possibly inside another call with another thread
    count)."""
    _RELEASED.append((pt, threads, mtype, arrays))


def max_threads() -> int:
    """MKL's current thread count (``MKL_Get_Max_Threads``)."""
    lib = library()
    return 0 if lib is None else int(lib.MKL_Get_Max_Threads())


@cache
def _openblas():  # -> threadpoolctl.ThreadpoolController | None
    """threadpoolctl's controller of the OpenBLAS (or BLIS) that NumPy and SciPy call, or None."""
    try:
        from threadpoolctl import ThreadpoolController
    except ImportError:  # pragma: no cover - a dependency
        return None
    controller = ThreadpoolController().select(internal_api=["openblas", "blis"])
    return controller if controller.lib_controllers else None


#: Holders of :func:`blas_one_thread` (threads of this process), the limit set while any holds it.
_blas_holders = 0
_blas_limiter = None  # threadpoolctl's limiter while held (it restores the counts it found)
_BLAS_LOCK = threading.Lock()


@contextlib.contextmanager
def blas_one_thread() -> Iterator[None]:
    """A context in which NumPy's own BLAS (OpenBLAS, not MKL) runs on one thread, while PARDISO
    runs on more than one: each runtime's idle threads spin for a while after a call, and one
    runtime's second thread then waits for the core another runtime's thread spins on. The
    Newton solves' vector products gain nothing from a second BLAS thread at these sizes. The
    limit must hold between the solves too (the line search's norms would wake OpenBLAS's
    threads), so the planner holds it for the whole plan. Does nothing where PARDISO never runs on
    more than one thread (a fixed count of 1, one core, or no MKL); a small system's factor runs on
    one thread anyway (:func:`~softgrasp.linalg.threads.factor_threads`). Reference-counted across
    threads: the counts found when the first holder entered are restored when the last one
    leaves."""
    global _blas_holders, _blas_limiter
    controller = _openblas() if choose_threads() > 1 and available() else None
    if controller is None:
        yield
        return
    with _BLAS_LOCK:
        if _blas_holders == 0:
            _blas_limiter = controller.limit(limits=1)
        _blas_holders += 1
    try:
        yield
    finally:
        with _BLAS_LOCK:
            _blas_holders -= 1
            if _blas_holders == 0 and _blas_limiter is not None:
                _blas_limiter.restore_original_limits()
                _blas_limiter = None
