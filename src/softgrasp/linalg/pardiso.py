"""Sparse symmetric factorisations by MKL PARDISO, with the symbolic analysis done once per pattern.

The Newton systems of softgrasp's static and implicit solvers keep the sparsity of the body's
Jacobian (the mesh's edges and tets) from one iteration, load step and holding step to the next;
only the values change. PARDISO (Intel oneMKL's parallel direct solver, the standard direct solver
of finite-element codes) splits the work into phases: the fill-reducing ordering and symbolic
factorisation (phase 11), the numerical factorisation (22) and the triangular solves (33).
:class:`PardisoFactor` runs phase 11 once for a pattern (and matrix type) and phase 22 for every
new matrix of that pattern: as matrix type 2 (Cholesky) while the matrices are positive definite,
as type -2 (real symmetric indefinite, Bunch-Kaufman pivoting) when one is not (a stiffness may
lose definiteness under compression, or be singular while a body is not held). At 7 576 nodes
the default plan took 10.1 s against 11.7 s with LDL^T throughout (alternating runs); at 2 196
nodes, whose settle leans through indefinite matrices, the two were level. The Newton solver needs
no inertia of an indefinite matrix, only a factor of its diagonally shifted, positive definite
neighbour: it stops at Cholesky's failure (``refactor(..., stop_if_indefinite=True)``) and
factorises the shift by :meth:`PardisoFactor.refactor_positive` (the default plan's settle at 2 196
nodes: 8 -> 6 factorisations and no LDL^T analysis, 1.35-1.40 -> 1.20-1.25 s a plan on one thread).

Mixed precision (``PardisoFactor(A, single=True)``, softgrasp's Newton solves by default): the
Cholesky factor is computed and applied in single precision (PARDISO's ``iparm[27]``), and the
caller refines every solve against the double-precision matrix (conjugate gradients or GMRES, as
it always did with an older factor used as a preconditioner). A factorisation takes ~0.63 of the
time, a solve ~0.67, the factor half the memory (2 196 nodes, one thread: 21 vs 33 ms and 0.54 vs
0.80 ms); the default plan there needed 30 more solves (232 vs 202: a fresh factor's own system is
refined to 1e-11) and ran 0.87-0.88 s against 0.99-1.04 s with double factors on two threads, the
same set-points to 1e-12. Where float32 cannot resolve
a matrix's pivots (the smallest below :data:`SINGLE_PIVOT_FLOOR` of its diagonal entry) or its
Cholesky fails, the double factorisation is made and decides, so that whether a matrix counts as
positive definite, indefinite or singular does not depend on the precision.

The library comes from the ``mkl`` wheel (x86_64); :func:`available` says whether it loaded, and
:mod:`softgrasp.linalg.solve` falls back to multigrid-preconditioned CG where it did not.

Threads (``SOFTGRASP_THREADS``: a number, or ``auto``, the default): PARDISO's OpenMP threads wait
for each other by spinning, so they pay only on cores nobody else is using. On this 2-core machine
two threads made the default plan at 2 196 nodes 1.4x faster when it was idle and 2x slower with
one other busy process (40x for a single solve in another measurement). ``auto`` therefore
chooses, when a pattern is analysed (PARDISO keeps that count through every later phase of the
pattern: changing it in between crashed MKL here), as many threads as there are cores not running
another process at that moment (Linux's count of runnable tasks in ``/proc/loadavg`` less this
process's own runnable threads; one thread where that is not available), and analyses again with
fewer threads when solves or factorisations find fewer cores idle several looks in a row (other
work started: two threads then made each solve ~10x slower here). MKL runs on Intel's OpenMP
runtime, whose idle threads spin for ``KMP_BLOCKTIME`` (its default 200 ms) after a solve before
they sleep: a Newton iteration's solves come faster than that, between other work, and each found
the threads awake. Measured on the default plan at 2 196 nodes, idle machine: with the threads
asleep at once (``KMP_BLOCKTIME=0``) a two-thread solve took 2.1 ms and a factorisation 32 ms,
slower than one thread; after 1 ms of spinning 1.6 ms; after 50-200 ms, 0.85-0.95 ms and 25 ms.
Their spinning is this process's own work, not another's: the looks leave it out.
:func:`set_threads` fixes a number.
"""

from __future__ import annotations

import contextlib
import ctypes
import glob
import hashlib
import math
import os
import sys
import threading
import time
from collections.abc import Iterator
from ctypes.util import find_library
from functools import cache

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

__all__ = ["PardisoError", "PardisoFactor", "available", "blas_one_thread", "idle_cores", "set_threads"]


#: MKL's code for its Intel OpenMP threading layer (``MKL_Set_Threading_Layer``).
MKL_THREADING_INTEL = 0

#: PARDISO's matrix type for real symmetric indefinite matrices (LDL^T, Bunch-Kaufman pivoting).
SYMMETRIC_INDEFINITE = -2
#: PARDISO's matrix type for real symmetric positive definite matrices (Cholesky).
SYMMETRIC_POSITIVE_DEFINITE = 2
#: After a matrix that was not positive definite, this many factorisations of the factor go
#: straight to the indefinite factorisation before Cholesky is tried again (a failed Cholesky
#: costs up to a factorisation).
SPD_RETRY = 4
#: A Cholesky factorisation with a pivot below this fraction of its matrix's diagonal entry counts
#: as not positive definite: PARDISO's Cholesky of a singular positive semi-definite stiffness
#: (a body not held: rigid motions free) succeeds with pivots ~1e-14 of the diagonal, reports
#: nothing, and its solves blow the free motions up. Such a matrix then gets the LDL^T factor it
#: had before Cholesky was used. (LDL^T does not flag it either: its pivot perturbation does not
#: scale with the matrix; a free foam cube's stiffness, diagonal ~1e5 N/m, gives
#: :attr:`PardisoFactor.perturbed_pivots` 0, the same matrix times 1e-9 gives 6.)
SPD_PIVOT_RTOL = 1e-8
#: A single-precision Cholesky factor (``PardisoFactor(..., single=True)``) is kept only when its
#: smallest pivot is at least this fraction of its matrix's diagonal entry; otherwise the matrix is
#: factorised in double precision, which gives the verdict (positive definite, indefinite or
#: singular) exactly as without single precision. A pivot d_k = a_kk - sum_j l_kj^2 d_j carries a
#: rounding error of about (a few) x float32's eps (6e-8) x a_kk, i.e. a relative error of
#: ~1e-7 / (d_k / a_kk): above this floor the single pivots are known to within a few percent, so
#: the single factor's verdict cannot differ from the double one's. The default plan's Cholesky
#: factors have ratios of 1e-2-2e-1 (2 196 nodes).
SINGLE_PIVOT_FLOOR = 1e-4
#: PARDISO's error code for a zero or negative pivot (a Cholesky of a matrix that is not positive
#: definite).
_ZERO_PIVOT = -4

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


#: Seconds between two looks at the machine's load from one factor's solves (reading
#: ``/proc/loadavg`` cost ~0.2 ms here, as much as a fifth of a solve at 2 000 nodes).
LOAD_CHECK_INTERVAL = 0.02
#: Consecutive looks that must find fewer idle cores before a factor drops threads, and looks
#: taken when a pattern is analysed (the most idle cores seen counts). On the idle machine about
#: 1 look in 100 sees a second runnable task for an instant (a system daemon): one look made
#: most plans at 2 196 nodes drop to one thread for good within their first second.
BUSY_LOOKS = 3
#: A look that finds fewer idle cores counts only when the last solve took more than this many
#: times the fastest of the factor's thread count (a core another process holds made two-thread
#: solves ~10x slower here; the default plan at 7 576 nodes, on the idle machine, dropped a thread
#: half-way for a kernel thread's runnable moments without it).
SLOW_SOLVE = 2.0


def _configured_threads() -> int | None:
    """The thread count ``SOFTGRASP_THREADS`` fixes, or None for ``auto``."""
    value = os.environ.get("SOFTGRASP_THREADS", "auto").strip().lower()
    if value in ("", "auto"):
        return None
    try:
        return max(1, int(value))
    except ValueError:
        return None


_fixed_threads: int | None = _configured_threads()
_current_threads = 0


def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def _own_runnable() -> int:
    """This process's threads that are running or runnable right now (>= 1: the caller's)."""
    n = 0
    for tid in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{tid}/stat", encoding="ascii") as fh:
                stat = fh.read()
        except OSError:  # the thread ended
            continue
        n += stat[stat.rindex(")") + 2] == "R"
    return max(n, 1)


def idle_cores() -> int:
    """Cores available to this process that no other process is running on right now (>= 1):
    the cores minus the runnable tasks (``/proc/loadavg``) that are not this process's threads
    (its own OpenMP threads spinning after a solve are not someone else's work); 1 where the
    counts cannot be read."""
    try:
        with open("/proc/loadavg", encoding="ascii") as fh:
            runnable = int(fh.read().split()[3].split("/")[0])
        own = _own_runnable()
    except (OSError, ValueError, IndexError):
        return 1
    return max(1, min(_cores(), _cores() - max(runnable - own, 0)))


def choose_threads() -> int:
    """Thread count for a new factor (and for the multigrid path's compiled products): fixed, or
    ``auto``: the idle cores (the most of :data:`BUSY_LOOKS` looks: another process that runs is
    seen in every look)."""
    if _fixed_threads is not None:
        return _fixed_threads
    return max(idle_cores() for _ in range(BUSY_LOOKS))


def _use_threads(lib: ctypes.CDLL, n: int) -> None:
    global _current_threads
    if n != _current_threads:
        lib.MKL_Set_Num_Threads(ctypes.c_int(n))
        _current_threads = n


#: Every PARDISO call and thread-count change is made holding this lock, so that calls from
#: several Python threads keep :data:`_current_threads` the count of the call being made (a
#: numerical factorisation run with another count than its pattern's analysis crashes MKL: a
#: segmentation fault, reproduced here; solves survived it).
_LOCK = threading.RLock()
#: Handles of collected factors waiting to be released: (handle, thread count, matrix type, the
#: arrays the handle was made with). A finaliser only appends here; the next PARDISO call
#: releases them.
_RELEASED: list[tuple[NDArray[np.int64], int, int, tuple[NDArray, ...]]] = []


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


@cache
def _library() -> ctypes.CDLL | None:
    """MKL's single dynamic library, or None where it is not installed."""
    names = [os.environ.get("SOFTGRASP_MKL_RT"), find_library("mkl_rt")]
    names += sorted(glob.glob(os.path.join(sys.prefix, "lib", "libmkl_rt.so*")), key=len)
    for name in names:
        if not name:
            continue
        try:
            lib = ctypes.CDLL(name)
            lib.pardiso  # noqa: B018 - the symbol must exist
            if not os.environ.get("MKL_THREADING_LAYER"):
                # Intel's OpenMP runtime (shipped with MKL) whatever was loaded before: MKL
                # otherwise takes GNU OpenMP where another library (gmsh) loaded it, which
                # KMP_BLOCKTIME does not reach. Before any other MKL call.
                lib.MKL_Set_Threading_Layer(ctypes.c_int(MKL_THREADING_INTEL))
            return lib
        except (OSError, AttributeError):
            continue
    return None


def set_threads(n: int | None) -> None:
    """Number of threads of the factorisations analysed from now on (>= 1); None: as
    ``SOFTGRASP_THREADS`` says (a number, or ``auto``)."""
    global _fixed_threads
    _fixed_threads = _configured_threads() if n is None else max(1, int(n))


def available() -> bool:
    """Whether MKL PARDISO could be loaded."""
    return _library() is not None


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
    runs on more than one: each runtime's idle threads spin for a while after a call, and on two
    cores OpenBLAS's second thread then waits for the core an MKL thread spins on (and the other
    way round). The Newton solves' vector products (GMRES, conjugate gradients) gain nothing from
    a second BLAS thread at these sizes. Measured on the default plan at 7 576 nodes, two PARDISO
    threads: 7.4-7.7 s with OpenBLAS's two threads, 4.6-4.7 s with one (one PARDISO thread:
    5.1-5.4 s); at 2 196 nodes within the machine's noise. The limit must hold between the solves
    too (the line search's norms woke OpenBLAS's thread: 6.8-7.3 s with it on the solves alone),
    so the planner holds it for the whole plan. Does nothing where PARDISO runs on one thread (a
    fixed count of 1, one core, or no MKL). Reference-counted across threads: the counts found
    when the first holder entered are restored when the last one leaves (the CLI's warm-up solves
    on a background thread while the plan starts)."""
    global _blas_holders, _blas_limiter
    threads = _fixed_threads if _fixed_threads is not None else _cores()
    controller = _openblas() if threads > 1 and available() else None
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


#: Nested-dissection orderings of the patterns analysed lately, by a digest of the pattern: a
#: body's Newton matrices keep one pattern from plan to plan (the symbolic analysis reused per
#: topology: METIS runs once).
_ORDERINGS: dict[bytes, NDArray[np.int32]] = {}
#: How many orderings are kept (each n 4-byte integers).
ORDERINGS_KEPT = 8


def _pattern_key(indptr: NDArray[np.int32], indices: NDArray[np.int32]) -> bytes:
    """A digest of a CSR pattern."""
    h = hashlib.blake2b(digest_size=20)
    h.update(np.int64(indptr.size).tobytes())
    h.update(indptr.tobytes())
    h.update(indices.tobytes())
    return h.digest()


_INT = ctypes.POINTER(ctypes.c_int32)
_DBL = ctypes.POINTER(ctypes.c_double)


def _keys(indptr: NDArray, indices: NDArray, n: int) -> NDArray[np.int64]:
    """Row-major keys ``row * n + col`` of a CSR pattern (ascending for sorted indices)."""
    rows = np.repeat(np.arange(n, dtype=np.int64), np.diff(indptr))
    return rows * n + indices.astype(np.int64)


class PardisoFactor:
    """The factorisation of a sparse symmetric matrix, refactorisable for new values of the same
    pattern.

    Parameters
    ----------
    A: (n, n) sparse symmetric matrix; only its upper triangle is read.
    single: factorise positive definite matrices in single precision (mixed precision: for
        callers that refine every solve against the double-precision matrix, as softgrasp's
        Newton solves do by conjugate gradients or GMRES; a solve's relative residual is then
        ~1e-4 instead of ~1e-12). At 2 196 nodes a factorisation took 21 instead of 33 ms and a
        solve 0.54 instead of 0.80 ms (one thread), half the factor's memory. A single factor is
        kept only when its smallest pivot is at least :data:`SINGLE_PIVOT_FLOOR` of its diagonal
        entry; otherwise (and always for LDL^T) the matrix is factorised in double precision, so
        the verdicts (positive definite, indefinite, singular) are the double factor's.
    """

    def __init__(self, A: sp.spmatrix, *, single: bool = False) -> None:
        lib = _library()
        if lib is None:
            raise PardisoError("MKL PARDISO is not installed (pip install mkl)")
        self._fn = lib.pardiso
        self._fn.restype = None
        # One PARDISO handle (and its iparm) per matrix type, each analysed when first used: a
        # matrix is factorised by Cholesky while it is positive definite (factorisation 1.2x
        # and solve 1.25x faster than LDL^T on two threads at 2 196 nodes), by LDL^T with
        # Bunch-Kaufman pivoting when it is not (a body about to tip, a singular stiffness).
        # Handles are keyed by (matrix type, single precision).
        self._pts: dict[tuple[int, bool], NDArray[np.int64]] = {}
        self._iparms: dict[tuple[int, bool], NDArray[np.int32]] = {}
        self._key = (SYMMETRIC_POSITIVE_DEFINITE, False)  # of the factorisation in use
        self._single = bool(single)
        self._data32: NDArray[np.float32] | None = None  # self._data in single precision
        self.factorisations = 0  # numerical factorisations made (both precisions)
        self.single_factorisations = 0  # of them in single precision and kept
        self.solves = 0  # solves made
        self._ready = False  # whether a factorisation is in use (the last one succeeded)
        self._skip_spd = 0  # factorisations by refactor() left before Cholesky is tried again
        self.n = int(A.shape[0])
        U = self._upper(A)
        self._indptr = U.indptr.astype(np.int32)
        self._indices = U.indices.astype(np.int32)
        self._data = np.ascontiguousarray(U.data, dtype=np.float64)
        # PARDISO sizes its work per thread in the analysis: every phase of this factor must run
        # with the same thread count (changing it in between crashed MKL here).
        self._threads = choose_threads()
        self._load_checked = time.monotonic()
        self._busy_looks = 0  # consecutive looks that found fewer idle cores than threads
        self._solve_times = [math.inf, math.inf]  # the fastest solve of this thread count, the last
        self._lib = lib
        # (indptr, indices) of the full pattern last seen by same_pattern, its upper entries and
        # their positions in this factor's data (None: every entry, in order).
        self._gather: tuple[NDArray, NDArray, NDArray, NDArray | None] | None = None
        self._perm: NDArray[np.int32] | None = None  # the fill-in reducing ordering, once analysed
        self._pattern = _pattern_key(self._indptr, self._indices)  # its key in _ORDERINGS
        self._factorise()

    @staticmethod
    def _new_iparm() -> NDArray[np.int32]:
        iparm = np.zeros(64, dtype=np.int32)
        iparm[0] = 1  # iparm given below (not defaults)
        iparm[1] = 2  # nested-dissection ordering (METIS)
        iparm[7] = 0  # no iterative refinement (the callers iterate on the true residual)
        iparm[9] = 8  # pivot perturbation 1e-8
        iparm[10] = 0  # no scaling (symmetric)
        iparm[12] = 0  # no weighted matching (symmetric)
        iparm[17] = -1  # report the factor's non-zeros in iparm[17]
        iparm[18] = -1  # report the factorisation's Mflop count in iparm[18]
        iparm[34] = 1  # zero-based indices
        return iparm

    def _analysed(self, key: tuple[int, bool]) -> None:
        """Analyse the pattern for handle ``key`` (matrix type, single precision), once."""
        if key not in self._pts:
            mtype, single = key
            self._pts[key] = np.zeros(64, dtype=np.int64)  # PARDISO's internal handle
            self._iparms[key] = iparm = self._new_iparm()
            if mtype == SYMMETRIC_POSITIVE_DEFINITE:
                iparm[55] = 1  # the factor's diagonal available (pardiso_getdiag)
            iparm[27] = 1 if single else 0  # matrix, right-hand side and solution in float32
            # The first analysis of a pattern returns its nested-dissection ordering; every
            # later one (the other matrix type's, the same pattern's in a later solve) takes it:
            # the same graph, the same ordering, without running METIS again (21 -> 9 ms an
            # analysis at 2 196 nodes).
            pattern = self._pattern
            if self._perm is None:
                with _LOCK:
                    self._perm = _ORDERINGS.get(pattern)
            iparm[4] = 2 if self._perm is None else 1
            perm = np.zeros(self.n, dtype=np.int32) if self._perm is None else self._perm
            self._call(11, key=key, perm=perm)
            perm.setflags(write=False)  # PARDISO only reads it from now on (iparm[4] = 1)
            self._perm = perm
            with _LOCK:
                _ORDERINGS.pop(pattern, None)
                _ORDERINGS[pattern] = perm  # the most recent last
                while len(_ORDERINGS) > ORDERINGS_KEPT:
                    del _ORDERINGS[next(iter(_ORDERINGS))]

    def _cholesky(self) -> str:
        """Cholesky factorisation of ``self._data``: ``"positive"`` (positive definite: the factor
        in use), ``"indefinite"`` (PARDISO met a non-positive pivot) or ``"singular"`` (a pivot
        below :data:`SPD_PIVOT_RTOL` of its diagonal entry). Unless positive, no factor is in use
        until the next factorisation. A single-precision factor is tried first where asked, and
        kept when its smallest pivot ratio is at least :data:`SINGLE_PIVOT_FLOOR`; otherwise the
        double one decides."""
        self._ready = False
        if self._single:
            key = (SYMMETRIC_POSITIVE_DEFINITE, True)
            if self._factorise_as(key) and self._min_pivot_ratio(key) >= SINGLE_PIVOT_FLOOR:
                self.single_factorisations += 1
                self._use(key)
                return "positive"
        key = (SYMMETRIC_POSITIVE_DEFINITE, False)
        if not self._factorise_as(key):
            return "indefinite"
        if self._min_pivot_ratio(key) < SPD_PIVOT_RTOL:
            return "singular"
        self._use(key)
        return "positive"

    def _factorise_as(self, key: tuple[int, bool]) -> bool:
        """Numerical factorisation of ``self._data`` by handle ``key``: False where PARDISO met a
        zero or negative pivot (no factor in use), True otherwise (not yet in use)."""
        self._ready = False
        self._analysed(key)
        self.factorisations += 1
        try:
            self._call(22, key=key)
        except PardisoError as exc:
            if exc.code != _ZERO_PIVOT:
                raise
            return False
        return True

    def _factorise(self, stop_if_indefinite: bool = False, ldlt: bool = False) -> bool:
        """Numerical factorisation of ``self._data``: Cholesky unless a recent matrix was not
        positive definite (then, or when Cholesky meets a non-positive pivot or a nearly singular
        matrix, LDL^T). The other type's factor is released (its analysis kept). With
        ``stop_if_indefinite``, a Cholesky that meets a non-positive pivot ends it: returns False,
        no factor in use (and Cholesky stays the first try: the caller factorises a shifted matrix
        next, not this one by LDL^T); otherwise True. ``ldlt``: LDL^T at once (Cholesky just
        failed on these values)."""
        if ldlt:
            self._skip_spd = SPD_RETRY
        elif self._skip_spd > 0:
            self._skip_spd -= 1
        else:
            verdict = self._cholesky()
            if verdict == "positive":
                return True
            if verdict == "indefinite" and stop_if_indefinite:
                return False
            self._skip_spd = SPD_RETRY  # LDL^T for a while, as before Cholesky
        key = (SYMMETRIC_INDEFINITE, False)
        self._ready = False
        self._analysed(key)
        self.factorisations += 1
        self._call(22, key=key)
        self._use(key)
        return True

    def _min_pivot_ratio(self, key: tuple[int, bool]) -> float:
        """The smallest pivot of the Cholesky factor of handle ``key`` over its matrix's diagonal
        entry."""
        dtype = np.float32 if key[1] else np.float64
        df = np.zeros(self.n, dtype=dtype)
        da = np.zeros(self.n, dtype=dtype)
        err = ctypes.c_int32(0)
        with _LOCK:
            self._lib.pardiso_getdiag(
                self._pts[key].ctypes.data_as(ctypes.POINTER(ctypes.c_int64)),
                df.ctypes.data_as(_DBL),
                da.ctypes.data_as(_DBL),
                ctypes.byref(ctypes.c_int32(1)),
                ctypes.byref(err),
            )
        if err.value != 0:
            return 0.0  # no diagonal: take the factorisation that reports its pivots
        return float(np.min(df.astype(np.float64) / np.where(da > 0.0, da, np.inf)))

    def _use(self, key: tuple[int, bool]) -> None:
        """Solve with the factor of handle ``key`` from now on; release the others' (phase 0:
        their L and U, not their analyses)."""
        self._key = key
        self._ready = True
        for other in self._pts:
            if other != key:
                self._call(0, key=other)

    @property
    def positive_definite(self) -> bool:
        """Whether the matrix last factorised was factorised by Cholesky (it was positive
        definite)."""
        return self._key[0] == SYMMETRIC_POSITIVE_DEFINITE

    @property
    def single_precision(self) -> bool:
        """Whether the factor in use is single precision (its solves ~1e-4 relative)."""
        return self._key[1]

    @staticmethod
    def _upper(A: sp.spmatrix) -> sp.csr_matrix:
        """The upper triangle of ``A`` in canonical CSR with every diagonal entry stored (PARDISO
        needs them, zero or not)."""
        n = A.shape[0]
        U = sp.triu(A, format="csr")
        U.sum_duplicates()
        U.sort_indices()
        counts = np.diff(U.indptr)
        if (counts > 0).all() and (U.indices[U.indptr[:-1]] == np.arange(n)).all():
            return U
        C = U.tocoo()
        i = np.arange(n)
        full = sp.coo_matrix(
            (np.concatenate([C.data, np.zeros(n)]), (np.concatenate([C.row, i]), np.concatenate([C.col, i]))),
            shape=(n, n),
        ).tocsr()  # duplicates summed, explicit zeros kept
        full.sort_indices()
        return full

    def _call(
        self,
        phase: int,
        b: NDArray[np.float64] | None = None,
        key: tuple[int, bool] | None = None,
        perm: NDArray[np.int32] | None = None,
    ) -> NDArray[np.float64]:
        """One PARDISO call of ``phase`` on handle ``key`` (default: the factor in use) with the
        current values; ``b``: the right-hand side of a solve. Returns the solution (in double
        precision) of a solve."""
        key = self._key if key is None else key
        mtype, single = key
        dtype = np.float32 if single else np.float64
        if single:
            if self._data32 is None:  # reset whenever _data is set
                self._data32 = self._data.astype(np.float32)
            data: NDArray = self._data32
        else:
            data = self._data
        x = np.zeros(self.n if b is not None else 1, dtype=dtype)
        rhs = np.ascontiguousarray(b, dtype=dtype) if b is not None else np.zeros(1, dtype=dtype)
        err = ctypes.c_int32(0)
        args = _arguments(
            self._pts[key],
            mtype,
            phase,
            data,
            self._indptr,
            self._indices,
            self._iparms[key],
            rhs,
            x,
            err,
            perm,
        )
        with _LOCK:
            # A collector run in between (any allocation may start one) only queues releases:
            # nothing changes the thread count between the next line and the call.
            _release_pending(self._lib)
            _use_threads(self._lib, self._threads)
            self._fn(*args)
        if err.value != 0:
            raise PardisoError(
                f"PARDISO phase {phase} failed: {_ERRORS.get(err.value, 'error')} ({err.value})", err.value
            )
        return x.astype(np.float64, copy=False)

    def same_pattern(self, A: sp.spmatrix) -> sp.csr_matrix | None:
        """The upper triangle of ``A`` in this factor's pattern (entries it lacks stored as zeros)
        if its non-zeros fit in that pattern, else None.

        A Newton solve hands in matrices of one full (both triangles) pattern over and over: the
        positions of that pattern's upper entries in this factor's are kept, and a matrix of the
        same pattern is then a gather of its values (no triangle extraction or search)."""
        if sp.issparse(A) and A.format == "csr" and A.has_canonical_format:
            gather = self._gather
            if (
                gather is not None
                and np.array_equal(A.indptr, gather[0])
                and np.array_equal(A.indices, gather[1])
            ):
                if gather[3] is None:  # the factor's pattern is A's upper triangle: one gather
                    data = A.data[gather[2]].astype(np.float64, copy=False)
                else:
                    data = np.zeros(self._indices.size)
                    data[gather[3]] = A.data[gather[2]]
                return sp.csr_matrix((data, self._indices, self._indptr), shape=A.shape)
            U = self._same_pattern(A)
            if U is not None:
                rows = np.repeat(np.arange(self.n, dtype=np.int64), np.diff(A.indptr))
                keep = np.flatnonzero(A.indices >= rows)
                keys = rows[keep] * self.n + A.indices[keep].astype(np.int64)
                pos = np.searchsorted(_keys(self._indptr, self._indices, self.n), keys)
                whole = pos.size == self._indices.size and bool((pos == np.arange(pos.size)).all())
                self._gather = (A.indptr.copy(), A.indices.copy(), keep, None if whole else pos)
            return U
        return self._same_pattern(A)

    def _same_pattern(self, A: sp.spmatrix) -> sp.csr_matrix | None:
        U = self._upper(A)
        if np.array_equal(U.indptr, self._indptr) and np.array_equal(U.indices, self._indices):
            return U
        keys = _keys(U.indptr, U.indices, self.n)
        mine = _keys(self._indptr, self._indices, self.n)
        pos = np.searchsorted(mine, keys)
        if (pos >= mine.size).any() or not np.array_equal(mine[pos], keys):
            return None
        data = np.zeros(mine.size)
        data[pos] = U.data
        return sp.csr_matrix((data, self._indices, self._indptr), shape=U.shape)

    @staticmethod
    def union(A: sp.spmatrix, B: sp.spmatrix) -> sp.csr_matrix:
        """``A`` with explicit zeros wherever ``B`` has entries and A does not (the pattern of both):
        factorised once, it takes either kind of matrix by :meth:`same_pattern`."""
        n = A.shape[0]
        C = sp.coo_matrix(A)
        zc = sp.coo_matrix(B)
        return sp.coo_matrix(
            (
                np.concatenate([C.data, 0.0 * zc.data]),
                (np.concatenate([C.row, zc.row]), np.concatenate([C.col, zc.col])),
            ),
            shape=(n, n),
        ).tocsr()  # duplicates summed, explicit zeros kept

    def matrix(self) -> sp.csr_matrix:
        """The upper triangle last factorised (its pattern and values)."""
        return sp.csr_matrix(
            (self._data.copy(), self._indices.copy(), self._indptr.copy()), shape=(self.n, self.n)
        )

    def refactor(self, U: sp.csr_matrix, *, stop_if_indefinite: bool = False, ldlt: bool = False) -> bool:
        """Numerical factorisation of new values ``U`` (from :meth:`same_pattern`). Returns True
        when their factor is in use; False only with ``stop_if_indefinite``, when Cholesky met a
        non-positive pivot (the matrix is not positive definite, and most likely indefinite; a
        singular one may also fail so: no factor is in use, and the caller factorises a shifted
        matrix by :meth:`refactor_positive`, or these values by LDL^T with ``ldlt``). The LDL^T
        that would otherwise follow, to count the negative pivots, is spared. ``ldlt``: LDL^T at
        once, no Cholesky tried."""
        self._set_values(U)
        if self._fewer_threads():
            return True
        return self._factorise(stop_if_indefinite, ldlt)

    def refactor_positive(self, U: sp.csr_matrix) -> bool:
        """Cholesky factorisation of new values ``U`` (a matrix shifted to be positive definite):
        True when it is (the factor in use), else False (no factor in use). Whatever the recent
        matrices were, Cholesky is tried: a shifted matrix is positive definite more often than
        not, and then its Cholesky is cheaper than LDL^T."""
        self._set_values(U)
        if self._fewer_threads() and self.positive_definite:
            return True
        return self._cholesky() == "positive"

    def _set_values(self, U: sp.csr_matrix) -> None:
        """Take the values of ``U``, which must be in this factor's pattern (:meth:`same_pattern`)."""
        if U.data.size != self._indices.size:
            raise PardisoError(
                f"values of another pattern: {U.data.size} entries for a factor of {self._indices.size}"
            )
        self._data = np.ascontiguousarray(U.data, dtype=np.float64)
        self._data32 = None

    @property
    def ready(self) -> bool:
        """Whether a factorisation is in use (False after a Cholesky stopped at a non-positive
        pivot, until the next factorisation succeeds)."""
        return self._ready

    def solve(self, b: NDArray[np.float64]) -> NDArray[np.float64]:
        """``A^-1 b`` for the matrix last factorised."""
        if not self._ready:
            raise PardisoError("no factorisation in use: the last one found the matrix not positive definite")
        self._fewer_threads()
        self.solves += 1
        t0 = time.perf_counter()
        if self.single_precision:
            # Scaled by a power of two (exact) to a largest entry in [1, 2): float32 would flush a
            # tiny right-hand side (a nearly balanced Newton step's) to zero or lose it to
            # subnormals.
            big = float(np.abs(b).max()) if b.size else 0.0
            scale = 2.0 ** math.floor(math.log2(big)) if big > 0.0 and math.isfinite(big) else 1.0
            x = self._call(33, b / scale) * scale
        else:
            x = self._call(33, b)
        dt = time.perf_counter() - t0
        self._solve_times = [min(self._solve_times[0], dt), dt]
        return x

    @property
    def values(self) -> NDArray[np.float64]:
        """The upper triangle's values last factorised (in the factor's CSR pattern)."""
        return self._data

    def _fewer_threads(self) -> bool:
        """With ``auto`` threads (looking at most every :data:`LOAD_CHECK_INTERVAL` seconds): if
        fewer cores are idle than this factor's threads, with the last solve slower than
        :data:`SLOW_SOLVE` times the fastest, in :data:`BUSY_LOOKS` looks in a row, analyse and
        factorise again with as many as are (other work started on the machine: spinning threads
        would make every solve many times slower). Returns whether it refactorised."""
        if self._threads == 1 or _fixed_threads is not None:
            return False
        now = time.monotonic()
        if now - self._load_checked < LOAD_CHECK_INTERVAL:
            return False
        self._load_checked = now
        n = idle_cores()
        fastest, last = self._solve_times
        if n >= self._threads or last <= SLOW_SOLVE * fastest:
            # Idle cores, or another task (a kernel thread: memory scanning) that did not slow
            # the last solve down.
            self._busy_looks = 0
            return False
        self._busy_looks += 1
        if self._busy_looks < BUSY_LOOKS:
            return False
        self._busy_looks = 0
        self._solve_times = [math.inf, math.inf]
        for key in self._pts:
            self._call(-1, key=key)  # release the memory of the old thread count
        self._pts, self._iparms = {}, {}
        self._threads = n
        self._factorise()
        return True

    @property
    def solves_per_factorisation(self) -> float:
        """The factorisation's floating-point operations over a solve's (4 per factor non-zero:
        forward and backward substitution): how many solves one factorisation costs in
        operations (not in time: see ``linsolve.SOLVE_SPEED_RATIO``)."""
        return max(1e6 * float(self._iparms[self._key][18]), 1.0) / max(4.0 * self.factor_nonzeros, 1.0)

    @property
    def factor_nonzeros(self) -> int:
        """Non-zeros of the factor (memory: about 8 bytes each)."""
        return int(self._iparms[self._key][17])

    @property
    def negative_pivots(self) -> int:
        """Negative eigenvalues seen in the factorisation (0: positive definite)."""
        if self.positive_definite:
            return 0
        return int(self._iparms[self._key][22])

    @property
    def perturbed_pivots(self) -> int:
        """Pivots perturbed because they were (nearly) zero: a singular matrix."""
        if self.positive_definite:
            return 0
        return int(self._iparms[self._key][13])

    def __del__(self) -> None:
        # The release is queued for the next PARDISO call, never made here: a finaliser runs
        # wherever the collector starts (inside another factor's call, after that call set its
        # thread count; on another Python thread during a call) and would set this factor's
        # thread count under the other's feet.
        try:
            for key, pt in self._pts.items():
                if pt.any():
                    arrays = (self._data, self._indptr, self._indices, self._iparms[key])
                    _RELEASED.append((pt, self._threads, key[0], arrays))
        except Exception:  # noqa: BLE001 - never raise from a finaliser
            pass
