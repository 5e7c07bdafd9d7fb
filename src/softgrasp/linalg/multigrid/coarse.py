"""The coarse levels of a kept multigrid hierarchy brought up to date with the contacts made since.

A smoothed-aggregation hierarchy is costly to build (many V-cycles' worth of work), so the
multigrid path keeps one across the Newton systems of a loading and swaps in each new matrix as
its finest level (:class:`softgrasp.linalg.multigrid.cycle.Multigrid`). Its coarse levels then lag behind
the contacts: a node pressed into the table since has a penalty stiffness tens of times its own,
which the coarse space, whose basis functions move that node with its whole aggregate, does not
know; fingertips pressing a few facets add stiffness there. The V-cycle still converges, but
GMRES or CG first spend several iterations finding those few modes, then converge at the rate of
a fresh hierarchy.

Two changes, each on a few nodes' neighbourhoods, bring the kept hierarchy back to that:

* the nodes whose stiffness grew past :data:`STIFFENED` times the build matrix's (contacts pinning
  them) leave the coarse space: the rows of the prolongator P for their unknowns are zeroed
  (P' = P with those rows zero), so the coarse correction leaves them alone and the smoother, for
  which a penalty-dominated node is an easy local problem, handles them. Keeping them in, their
  new stiffness summed into the coarse operator, is worse than stale (the penalty spread over the
  aggregate pins it);
* the coarse operators follow the stiffness the nodes whose diagonal moved by more than
  :data:`CHANGED` gained or lost (the fingertips' contacts, distributed by shape functions, add
  5-50 % to a handful of nodes): the Galerkin products of P' with the build matrix plus that
  change (:func:`galerkin_change`). The change is taken among those nodes, its couplings to the
  other nodes moved onto their diagonal blocks so that a rigid translation meets it as it meets
  the whole change; taken as it is in their rows and columns, the edge of the patch would break
  the operator's rigid modes.

The second level's operator changes by a sparse matrix computed on those nodes and their
neighbours alone, deeper levels by its Galerkin products; the operators are changed in place
(:class:`UpdatedLevel`). The updated levels take about as many iterations as a fresh hierarchy
would, for a fraction of its set-up.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

__all__ = ["STIFFENED", "CHANGED", "MAX_CHANGED", "UpdatedLevel", "changed_nodes", "galerkin_change"]

#: A node whose largest diagonal stiffness grew past this factor of the build matrix's leaves the
#: coarse space (a contact's penalty pins it).
STIFFENED = 1.5
#: A node whose diagonal stiffness moved by more than this fraction of the build matrix's has its
#: current stiffness in the coarse operators (a fingertip's contact adds 5-50 % to a few nodes;
#: the sag and roll of a ball settling on the table change thousands by 0.2-2 %, which the
#: operators need not follow).
CHANGED = 0.05
#: At most this many changed nodes (the largest changes) are followed: the update's cost grows
#: with them, its gain does not.
MAX_CHANGED = 1000


def changed_nodes(
    diagonal: NDArray[np.float64], diagonal0: NDArray[np.float64]
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """The nodes (3 unknowns each, ``x, y, z``) whose stiffness the contacts changed since the
    build matrix, from the current and the build matrix's diagonals (3N,), each entry's ratio to
    its build value taken relative to the median node's (a stiffness changed throughout, as by a
    scaled matrix or a stiffening material, is not a contact, and pinning every node would make
    the coarse levels useless). Returns (the stiffened
    nodes: some diagonal entry grew past :data:`STIFFENED` times that; the changed ones: some
    entry moved by more than :data:`CHANGED` of it), each at most :data:`MAX_CHANGED`, the
    largest. An entry that was not positive counts as changed when it differs at all."""
    d = np.asarray(diagonal, dtype=np.float64)
    d0 = np.asarray(diagonal0, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = d / d0
    odd = np.flatnonzero(~(d0 > 0))  # few or none
    ratio[odd] = np.where(d[odd] == d0[odd], 1.0, np.inf)
    x, y, z = ratio[0::3], ratio[1::3], ratio[2::3]
    high = np.maximum(np.maximum(x, y), z)
    low = np.minimum(np.minimum(x, y), z)
    typical = float(np.median(high))
    if np.isfinite(typical) and typical > 0 and typical != 1.0:
        high, low = high / typical, low / typical
    moved = np.maximum(high - 1.0, 1.0 - low)
    return _largest(high, STIFFENED), _largest(moved, CHANGED)


def _largest(value: NDArray[np.float64], floor: float) -> NDArray[np.intp]:
    """The nodes whose ``value`` exceeds ``floor``, at most :data:`MAX_CHANGED` of them (the
    largest values), in order."""
    nodes = np.flatnonzero(value > floor)
    if nodes.size > MAX_CHANGED:
        nodes = np.sort(nodes[np.argsort(value[nodes], kind="stable")[-MAX_CHANGED:]])
    return nodes


def _dofs(nodes: NDArray[np.intp]) -> NDArray[np.intp]:
    return (3 * np.asarray(nodes, dtype=np.intp)[:, None] + np.arange(3)).ravel()


def galerkin_change(
    P: sp.spmatrix | sp.sparray,
    A0: sp.csr_matrix,
    A: sp.csr_matrix,
    stiffened: NDArray[np.intp],
    changed: NDArray[np.intp],
) -> sp.csr_matrix:
    """The change of the second level's Galerkin operator, ``P'^T (A0 + D) P' - P^T A0 P``, where
    ``P`` (n x nc) is the prolongator from the finest level, ``A0`` the matrix the hierarchy was
    built on, ``P'`` is ``P`` with the rows of the ``stiffened`` nodes' unknowns zeroed, and ``D``
    is the change ``A - A0`` among the ``changed`` nodes: its entries between two changed nodes,
    and each entry coupling a changed node i to another node j moved onto i's diagonal block (row
    and column component kept), then symmetrised. ``D t`` is then ``(A - A0) t`` on the changed
    nodes for a rigid translation ``t`` wherever the change's 3 x 3 blocks are symmetric (springs,
    contacts), and ``A0 + D`` keeps ``A0``'s other rows.

    With ``P = P' + Ps`` (Ps: the stiffened rows of P),

        P'^T (A0 + D) P' - P^T A0 P = P'^T D P' - P^T (A0 Ps) - Ps^T A0 P',

    where ``A0 Ps`` has entries only in the rows of the stiffened nodes' neighbours: every product
    is formed on the unknowns of the stiffened and changed nodes and their neighbours (``A0``'s
    and ``A``'s patterns) alone. Returns a CSR (nc x nc) matrix, zero outside the coarse unknowns
    whose basis functions reach those nodes."""
    n, nc = P.shape
    touched = np.union1d(stiffened, changed)
    if touched.size == 0:
        return sp.csr_matrix((nc, nc))
    rows = _dofs(touched)
    near = np.union1d(A0[rows].indices, A[rows].indices) // 3
    U = _dofs(np.union1d(near, touched))
    A0u = A0[U][:, U].tocsr()
    on = np.zeros(n // 3, dtype=bool)
    on[changed] = True
    in_changed = on[U // 3]
    D = (A[U][:, U] - A0u).tocoo()
    # D: the change among the changed nodes, a coupling to another node moved onto the changed
    # node's diagonal block (the same row, the column's component), symmetrised.
    both = in_changed[D.row] & in_changed[D.col]
    cut = in_changed[D.row] & ~in_changed[D.col]
    lumped = 3 * (D.row[cut] // 3) + D.col[cut] % 3  # U holds each node's three unknowns in a row
    D = sp.csr_matrix(
        (
            np.concatenate([D.data[both], D.data[cut]]),
            (np.concatenate([D.row[both], D.row[cut]]), np.concatenate([D.col[both], lumped])),
        ),
        shape=A0u.shape,
    )
    D = 0.5 * (D + D.T)
    on[:] = False
    on[stiffened] = True
    pinned = on[U // 3].astype(np.float64)
    Pu = _rows(P, U)
    Ps = sp.diags(pinned) @ Pu
    Pm = Pu - Ps
    change = Pm.T @ (D @ Pm) - Pu.T @ (A0u @ Ps) - (Ps.T @ A0u) @ Pm
    return sp.csr_matrix(change)


def _rows(P: sp.spmatrix | sp.sparray, rows: NDArray[np.intp]) -> sp.csr_matrix:
    """Rows ``rows`` of ``P`` as CSR; read straight from the arrays of a BSR matrix of 1 x k
    blocks (the prolongator from the finest level, kept in that form only)."""
    if P.format != "bsr" or P.blocksize[0] != 1:
        return sp.csr_matrix(sp.csr_matrix(P)[rows])
    k = P.blocksize[1]
    start = np.asarray(P.indptr, dtype=np.int64)[rows]
    count = np.asarray(P.indptr, dtype=np.int64)[rows + 1] - start
    offsets = np.repeat(start - np.concatenate([[0], np.cumsum(count)[:-1]]), count)
    at = offsets + np.arange(int(count.sum()))
    indices = (np.asarray(P.indices, dtype=np.int64)[at][:, None] * k + np.arange(k)).ravel()
    indptr = np.concatenate([[0], np.cumsum(count * k)])
    return sp.csr_matrix((P.data[at].reshape(-1), indices, indptr), shape=(rows.size, P.shape[1]))


class UpdatedLevel:
    """A coarse level's operator as built plus a sparse change (:func:`galerkin_change` and its
    Galerkin products), changed in place: the blocks a change touches are saved, changed, and put
    back before the next change (no copy of the operator: the 27 749-node sphere's second level is
    20 MB); its block Gauss-Seidel ``sweeps`` (for all levels but the coarsest) likewise, their
    diagonal inverses recomputed for the changed block rows only.

    ``matrix`` is a canonical BSR matrix of square blocks (the one ``sweeps`` read, if given). A
    change with a block outside its pattern (a Galerkin product's pattern holds every block its
    matrices can reach, so it does not arise) is added by SciPy into a new matrix instead.
    """

    def __init__(self, matrix: sp.bsr_matrix | sp.bsr_array, sweeps: Any = None) -> None:
        if sweeps is not None:
            matrix = sweeps.A  # the canonical matrix the sweeps read
        elif not matrix.has_canonical_format:
            matrix = matrix.copy()
            matrix.sum_duplicates()
        self._matrix = matrix
        self._sweeps = sweeps
        b = matrix.blocksize[0]
        self._b = b
        nb = matrix.shape[0] // b
        rows = np.repeat(np.arange(nb, dtype=np.int64), np.diff(matrix.indptr))
        self._keys = rows * nb + np.asarray(matrix.indices, dtype=np.int64)
        self._positions = np.zeros(0, dtype=np.int64)
        self._saved = np.zeros((0, b, b))
        self._rows = np.zeros(0, dtype=np.int64)
        self._saved_inverse = np.zeros((0, b, b))
        self._other: tuple[Any, Any] | None = None  # (matrix, sweeps) made for a change off the pattern
        self.changed = False

    @property
    def matrix(self) -> Any:
        """The operator now."""
        return self._matrix if self._other is None else self._other[0]

    @property
    def sweeps(self) -> Any:
        """Its sweeps now (None for the coarsest level)."""
        return self._sweeps if self._other is None else self._other[1]

    def reset(self) -> None:
        """Back to the operator as built."""
        self._matrix.data[self._positions] = self._saved
        if self._sweeps is not None:
            self._sweeps.inverse_diagonal[self._rows] = self._saved_inverse
        self._positions, self._saved = self._positions[:0], self._saved[:0]
        self._rows, self._saved_inverse = self._rows[:0], self._saved_inverse[:0]
        self._other = None
        self.changed = False

    def update(self, change: sp.spmatrix | sp.sparray) -> None:
        """The operator as built plus ``change`` (of its shape)."""
        self.reset()
        b = self._b
        nb = self._matrix.shape[0] // b
        C = sp.bsr_matrix(change, blocksize=(b, b))
        C.sum_duplicates()
        crows = np.repeat(np.arange(nb, dtype=np.int64), np.diff(C.indptr))
        keys = crows * nb + np.asarray(C.indices, dtype=np.int64)
        at = np.searchsorted(self._keys, keys)
        self.changed = True
        if not np.array_equal(self._keys[np.minimum(at, self._keys.size - 1)], keys):
            matrix = (self._matrix + C).tobsr(blocksize=(b, b))
            sweeps = None
            if self._sweeps is not None:
                from softgrasp.linalg.smoothers import BlockGaussSeidel

                sweeps = BlockGaussSeidel(matrix, self._sweeps.threads)
            self._other = (matrix, sweeps)
            return
        self._positions = at
        self._saved = self._matrix.data[at].copy()
        self._matrix.data[at] += C.data
        if self._sweeps is not None:
            self._rows = np.unique(crows)
            self._saved_inverse = self._sweeps.inverse_diagonal[self._rows].copy()
            self._sweeps.invert_rows(self._rows)
