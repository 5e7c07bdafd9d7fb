"""The Newton matrix of a static solve, assembled in the body's fixed sparsity pattern, and the
product with the exact Newton matrix where an interaction's Jacobian is only a symmetrised
approximation (a forward difference of its forces replaces that part of the product).
"""

from __future__ import annotations

import functools
import weakref
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from softgrasp.physics.body import Body
from softgrasp.sim.scene import Scene

__all__ = ["newton_matrix", "ExactProduct", "FD_STEP"]

#: Largest nodal displacement of the forward difference in the exact Newton product, as a fraction
#: of the body's size. Its truncation error relative to the product is about the step over the
#: shallowest contact depth (1e-5 at 0.1 mm on a 128 mm body), its round-off about 1e-16 times the
#: inverse (1e-11): both far below the Newton solves' forcing term (<= 1e-4). One contact
#: evaluation per product instead of the two of a central difference.
FD_STEP = 1e-8


@dataclass(frozen=True)
class _BodyPattern:
    """Where the entries of a body's Jacobian pattern sit in its CSR data.

    Attributes
    ----------
    keys: sorted keys ``3N row + col`` of the scalar entries, in CSR data order, (nnz,).
    diagonal: the data positions of each node's diagonal 3x3 block, row by row, (N, 9).
    """

    keys: NDArray[np.int64]
    diagonal: NDArray[np.int64]


_PATTERNS: weakref.WeakKeyDictionary[Body, dict[bool, _BodyPattern]] = weakref.WeakKeyDictionary()


def _body_pattern(body: Body, exact: bool = False) -> _BodyPattern:
    """The :class:`_BodyPattern` of ``body``'s Newton Jacobian (``exact``: as
    :meth:`~softgrasp.physics.body.Body.newton_jacobian`; built once, kept while the body lives)."""
    kept = _PATTERNS.setdefault(body, {})
    pat = kept.get(exact)
    if pat is None:
        J = body.newton_jacobian(np.asarray(body.mesh.points, dtype=np.float64), exact=exact)
        n = J.shape[0]
        rows = np.repeat(np.arange(n, dtype=np.int64), np.diff(J.indptr))
        keys = rows * n + J.indices.astype(np.int64)
        i = 3 * np.arange(body.n_nodes, dtype=np.int64)
        a = np.arange(3)
        want = ((i[:, None, None] + a[None, :, None]) * n + i[:, None, None] + a[None, None, :]).reshape(
            -1, 9
        )
        diagonal = np.searchsorted(keys, want)
        if not np.array_equal(keys[np.minimum(diagonal, keys.size - 1)], want):
            raise AssertionError("a node without its diagonal block in the body's Jacobian pattern")
        pat = kept[exact] = _BodyPattern(keys, diagonal)
    return pat


def _add_into_pattern(
    pat: _BodyPattern, data: NDArray[np.float64], M: sp.spmatrix
) -> tuple[sp.csr_matrix, sp.csr_matrix | None]:
    """Add the entries of ``M`` that lie in the body's pattern to its CSR ``data`` (in place).
    Returns (those entries, the others or None) as sparse matrices."""
    M = sp.csr_matrix(M)
    M.sum_duplicates()
    n = M.shape[0]
    rows = np.repeat(np.arange(n, dtype=np.int64), np.diff(M.indptr))
    cols = M.indices.astype(np.int64)
    keys = rows * n + cols
    pos = np.minimum(np.searchsorted(pat.keys, keys), pat.keys.size - 1)
    inside = pat.keys[pos] == keys
    data[pos[inside]] += M.data[inside]
    kept = sp.csr_matrix((M.data[inside], (rows[inside], cols[inside])), shape=M.shape)
    if inside.all():
        return kept, None
    out = ~inside
    return kept, sp.csr_matrix((M.data[out], (rows[out], cols[out])), shape=M.shape)


def _static_forces_of(inter, body: Body, t: float, st, x: NDArray[np.float64]) -> NDArray[np.float64]:
    return inter.static_forces(body, x, t, st)


def newton_matrix(
    scene: Scene,
    x: NDArray[np.float64],
    t: float,
    contacts: tuple,
    L: float,
    threads: int = 1,
    exact_body: bool = False,
) -> tuple[sp.csr_matrix, Callable[[NDArray[np.float64]], NDArray[np.float64]] | None]:
    """The Newton matrix A = -d f / d x as assembled (symmetric: interactions whose Jacobian is a
    symmetrised approximation contribute that; the body's as
    :meth:`~softgrasp.physics.body.Body.newton_jacobian` with ``exact_body``), and, where there
    are such interactions or the body's is approximate, the product with the exact matrix: their
    part of ``A v`` replaced by a forward difference of their forces along v. (A Newton iteration
    with the symmetrised matrix converges only linearly, about tenfold per iteration; with the
    exact product, quadratically.)"""
    body = scene.body
    J = body.newton_jacobian(x, threads=threads, exact=exact_body)  # in the body's fixed pattern, data fresh
    pat = _body_pattern(body, exact_body)
    data = J.data
    approx = []
    outside: list[sp.csr_matrix] = []
    # Each interaction's Jacobian is summed straight into the body pattern's data, in the
    # interactions' order (the same sums, entry by entry, as adding the sparse matrices), so
    # that every Newton matrix has one pattern: no sparse additions, and the factorisation's
    # analysis and its gather of the upper triangle are reused as they are.
    for inter, st in zip(scene.interactions, contacts, strict=True):
        diagonal = getattr(inter, "jacobian_diagonal", None)
        if diagonal is not None:
            nodes, blocks = diagonal(body, x, t, st)
            data[pat.diagonal[nodes]] += blocks.reshape(-1, 9)
            continue
        Ji = inter.jacobian(body, x, t, st)
        if not Ji.nnz:
            continue
        kept, rest = _add_into_pattern(pat, data, Ji)
        if not getattr(inter, "symmetric_jacobian", True):
            # Only a preconditioner now: kept inside the body's pattern, so that the factorisation's
            # analysis stays valid as contacts come and go.
            pinned = getattr(inter, "pinned_static_forces", None)
            if pinned is not None:
                forces_at = pinned(body, x, t, st)
            else:
                forces_at = functools.partial(_static_forces_of, inter, body, t, st)
            approx.append((forces_at, kept))
        elif rest is not None:
            outside.append(rest)  # couples nodes that no edge or tet joins
    np.negative(data, out=data)
    A = J
    for M in outside:
        A = A - M
    A = A.tocsr()
    body_part = body.newton_correction(x, exact=exact_body)
    if not approx and body_part is None:
        return A, None
    return A, ExactProduct(A, approx, x, L, () if body_part is None else (body_part,))


class ExactProduct:
    """The product with the exact Newton matrix: ``matrix @ v`` with the approximated
    interactions' part of it replaced by a forward difference of their forces along v, and the
    body's approximated part (:meth:`~softgrasp.physics.body.Body.newton_correction`, ``exact``)
    by its exact product, i.e. ``correction(v, matrix @ v)`` (a solver with a faster product of
    ``matrix`` applies that and passes it to :meth:`correction`)."""

    def __init__(
        self, A: sp.csr_matrix, approx: list, x: NDArray[np.float64], L: float, exact: tuple = ()
    ) -> None:
        self.matrix = A
        self._approx = approx
        self._exact = exact
        self._x = x
        self._L = L
        self._base: list[NDArray[np.float64]] = []

    def correction(self, v: NDArray[np.float64], out: NDArray[np.float64]) -> NDArray[np.float64]:
        """Add to ``out`` (``matrix @ v``) what turns it into the exact product: for each
        approximated interaction, its matrix part taken back out and the forward difference of its
        forces along v put in. Returns ``out``."""
        for add in self._exact:
            add(v, out)
        V = v.reshape(-1, 3)
        vmax = float(np.abs(V).max())
        if vmax == 0 or not self._approx:
            return out
        h = FD_STEP * self._L / vmax
        if not self._base:
            self._base.extend(forces_at(self._x) for forces_at, _ in self._approx)
        for (forces_at, Ji), f0 in zip(self._approx, self._base, strict=True):
            out += Ji @ v - ((forces_at(self._x + h * V) - f0) / h).ravel()
        return out

    def __call__(self, v: NDArray[np.float64]) -> NDArray[np.float64]:
        return self.correction(v, self.matrix @ v)

