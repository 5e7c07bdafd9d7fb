"""Sparse symmetric factorisations by MKL PARDISO, with the symbolic analysis done once per pattern.

The Newton systems of softgrasp's static and implicit solvers keep the sparsity of the body's
Jacobian (the mesh's edges and tets) from one iteration, load step and holding step to the next;
only the values change. PARDISO (Intel oneMKL's parallel direct solver, the standard direct solver
of finite-element codes) splits the work into phases: the fill-reducing ordering and symbolic
factorisation (phase 11), the numerical factorisation (22) and the triangular solves (33).
:class:`PardisoFactor` runs phase 11 once for a pattern (and matrix type) and phase 22 for every
new matrix of that pattern: as matrix type 2 (Cholesky) while the matrices are positive definite,
as type -2 (real symmetric indefinite, Bunch-Kaufman pivoting) when one is not (a stiffness may
lose definiteness under compression, or be singular while a body is not held). The Newton solver
needs no inertia of an indefinite matrix, only a factor of its diagonally shifted, positive
definite neighbour: it stops at Cholesky's failure (``refactor(..., stop_if_indefinite=True)``)
and factorises the shift by :meth:`PardisoFactor.refactor_positive`.

Mixed precision (``PardisoFactor(A, single=True)``, softgrasp's Newton solves by default): the
Cholesky factor is computed and applied in single precision (PARDISO's ``iparm[27]``), and the
caller refines every solve against the double-precision matrix (conjugate gradients or GMRES).
A factorisation and a solve take about two thirds of the time, the factor half the memory. Where
float32 cannot resolve a matrix's pivots (the smallest below :data:`SINGLE_PIVOT_FLOOR` of its
diagonal entry) or its Cholesky fails, the double factorisation is made and decides, so that
whether a matrix counts as positive definite, indefinite or singular does not depend on the
precision.

The library and the calls are :mod:`softgrasp.linalg.mkl`'s; a factor runs on the thread count
:func:`factor_threads` gives when its pattern is analysed, through every later phase.
"""

from __future__ import annotations

import hashlib
import math
import threading

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from softgrasp.linalg import mkl
from softgrasp.linalg.mkl import PardisoError, available, blas_one_thread
from softgrasp.linalg.threads import choose_threads, factor_threads, fixed_threads, set_threads

# What callers reach through this module: the factor, its error, MKL's state and the threads.
__all__ = ["PardisoError", "PardisoFactor", "available", "blas_one_thread"]
__all__ += ["choose_threads", "factor_threads", "fixed_threads", "set_threads"]

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
#: nothing, and its solves blow the free motions up. Such a matrix then gets an LDL^T factor
#: (whose pivot perturbation, not scaled with the matrix, need not flag it either).
SPD_PIVOT_RTOL = 1e-8
#: A single-precision Cholesky factor (``PardisoFactor(..., single=True)``) is kept only when its
#: smallest pivot is at least this fraction of its matrix's diagonal entry; otherwise the matrix is
#: factorised in double precision, which gives the verdict (positive definite, indefinite or
#: singular) exactly as without single precision. A pivot d_k = a_kk - sum_j l_kj^2 d_j carries a
#: rounding error of about (a few) x float32's eps (6e-8) x a_kk, i.e. a relative error of
#: ~1e-7 / (d_k / a_kk): above this floor the single pivots are known to within a few percent, so
#: the single factor's verdict cannot differ from the double one's.
SINGLE_PIVOT_FLOOR = 1e-4
#: PARDISO's error code for a zero or negative pivot (a Cholesky of a matrix that is not positive
#: definite).
_ZERO_PIVOT = -4

#: Nested-dissection orderings of the patterns analysed lately, by a digest of the pattern: a
#: body's Newton matrices keep one pattern from plan to plan (the symbolic analysis reused per
#: topology: METIS runs once).
_ORDERINGS: dict[bytes, NDArray[np.int32]] = {}
#: How many orderings are kept (each n 4-byte integers).
ORDERINGS_KEPT = 8
_ORDERINGS_LOCK = threading.Lock()


def _pattern_key(indptr: NDArray[np.int32], indices: NDArray[np.int32]) -> bytes:
    """A digest of a CSR pattern."""
    h = hashlib.blake2b(digest_size=20)
    h.update(np.int64(indptr.size).tobytes())
    h.update(indptr.tobytes())
    h.update(indices.tobytes())
    return h.digest()


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
        ~1e-4 instead of ~1e-12), for about two thirds of the time and half the memory. A single
        factor is kept only when its smallest pivot is at least :data:`SINGLE_PIVOT_FLOOR` of its
        diagonal entry; otherwise (and always for LDL^T) the matrix is factorised in double precision, so
        the verdicts (positive definite, indefinite, singular) are the double factor's.
    """

    def __init__(self, A: sp.spmatrix, *, single: bool = False) -> None:
        if not available():
            raise PardisoError("MKL PARDISO is not installed (pip install mkl)")
        # One PARDISO handle (and its iparm) per matrix type, each analysed when first used: a
        # matrix is factorised by Cholesky while it is positive definite (faster than LDL^T), by
        # LDL^T with Bunch-Kaufman pivoting when it is not (a body about to tip, a singular
        # stiffness).
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
        self._threads = factor_threads(self.n)
        # (indptr, indices) of the full pattern last seen by same_pattern, its upper entries and
        # their positions in this factor's data (None: every entry, in order).
        self._gather: tuple[NDArray, NDArray, NDArray, NDArray | None] | None = None
        self._perm: NDArray[np.int32] | None = None  # the fill-in reducing ordering, once analysed
        self._pattern = _pattern_key(self._indptr, self._indices)  # its key in _ORDERINGS
        self._factorise()

    def _new_iparm(self) -> NDArray[np.int32]:
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
        iparm[33] = self._threads  # reproducible results on this many threads (MKL's CNR mode)
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
            # the same graph, the same ordering, without running METIS again.
            pattern = self._pattern
            if self._perm is None:
                with _ORDERINGS_LOCK:
                    self._perm = _ORDERINGS.get(pattern)
            iparm[4] = 2 if self._perm is None else 1
            perm = np.zeros(self.n, dtype=np.int32) if self._perm is None else self._perm
            self._call(11, key=key, perm=perm)
            perm.setflags(write=False)  # PARDISO only reads it from now on (iparm[4] = 1)
            self._perm = perm
            with _ORDERINGS_LOCK:
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
        if mkl.get_diagonal(self._pts[key], df, da) != 0:
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
        code = mkl.call(
            self._threads,
            self._pts[key],
            mtype,
            phase,
            data,
            self._indptr,
            self._indices,
            self._iparms[key],
            rhs,
            x,
            perm=perm,
        )
        if code != 0:
            raise PardisoError.of(phase, code)
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
        return self._factorise(stop_if_indefinite, ldlt)

    def refactor_positive(self, U: sp.csr_matrix) -> bool:
        """Cholesky factorisation of new values ``U`` (a matrix shifted to be positive definite):
        True when it is (the factor in use), else False (no factor in use). Whatever the recent
        matrices were, Cholesky is tried: a shifted matrix is positive definite more often than
        not, and then its Cholesky is cheaper than LDL^T."""
        self._set_values(U)
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
        self.solves += 1
        if self.single_precision:
            # Scaled by a power of two (exact) to a largest entry in [1, 2): float32 would flush a
            # tiny right-hand side (a nearly balanced Newton step's) to zero or lose it to
            # subnormals.
            big = float(np.abs(b).max()) if b.size else 0.0
            scale = 2.0 ** math.floor(math.log2(big)) if big > 0.0 and math.isfinite(big) else 1.0
            x = self._call(33, b / scale) * scale
        else:
            x = self._call(33, b)
        return x

    @property
    def values(self) -> NDArray[np.float64]:
        """The upper triangle's values last factorised (in the factor's CSR pattern)."""
        return self._data

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
                    mkl.release_later(pt, self._threads, key[0], arrays)
        except Exception:  # noqa: BLE001 - never raise from a finaliser
            pass
