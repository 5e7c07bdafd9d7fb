"""The smoothed-aggregation hierarchy of a body's Newton matrix (pyamg), reproducible run to run.

pyamg's classical smoothed aggregation builds it (``smoothed_aggregation_solver``: symmetric
strength, standard aggregation, Jacobi-smoothed prolongators, coarsening to :data:`MAX_COARSE`
block rows). The near-null space is the body's six rigid-body modes, the standard choice for elasticity. pyamg
estimates a spectral radius from a random start while it builds the hierarchy: the start is drawn
from NumPy's global generator seeded with :data:`AMG_SEED` under a lock, so that the same matrix
gives the same hierarchy and a plan the same numbers, whichever threads build hierarchies at once.
"""

from __future__ import annotations

import os
import threading
from typing import Any

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

__all__ = ["AMG_SEED", "MAX_COARSE", "POSTSMOOTHER", "PRESMOOTHER", "hierarchy", "rigid_modes"]


def rigid_modes(x: NDArray[np.float64]) -> NDArray[np.float64]:
    """The six rigid-body modes (three translations, three rotations about the centroid) of the
    nodes ``x`` (n, 3), as columns of a (3 n, 6) array."""
    n = x.shape[0]
    B = np.zeros((3 * n, 6))
    for k in range(3):
        B[k::3, k] = 1.0
    r = x - x.mean(axis=0)
    for k, (i, j) in enumerate(((0, 1), (1, 2), (2, 0))):
        B[i::3, 3 + k] = -r[:, j]
        B[j::3, 3 + k] = r[:, i]
    return B


#: The multigrid V-cycle's smoothing on every level pyamg sweeps: one forward (block) Gauss-Seidel
#: sweep before the coarse correction, one backward after (a symmetric preconditioner, as
#: conjugate gradients need; the finest level's sweeps are softgrasp's own where the compiled
#: kernels are in use, :class:`~softgrasp.linalg.smoothers.HybridGaussSeidel`). A symmetric sweep
#: on each side (pyamg's default) costs half as much again a cycle for about one iteration fewer.
PRESMOOTHER = ("block_gauss_seidel", {"sweep": "forward"})
POSTSMOOTHER = ("block_gauss_seidel", {"sweep": "backward"})
#: The coarsest level's most block rows (factorised by sparse LU).
MAX_COARSE = 300
#: Seed of the random start from which pyamg estimates a spectral radius while it builds a
#: hierarchy (NumPy's global generator, seeded and put back: a hierarchy should not be built
#: while another Python thread draws from it; softgrasp's own threads build theirs one at a time,
#: :data:`_GLOBAL_RNG`).
AMG_SEED = 20_240_901
#: Held while a hierarchy is built from NumPy's seeded global generator: two threads planning at
#: once (a script's thread pool) would otherwise draw from each other's seeded sequence, and each
#: plan's numbers would depend on how the threads interleaved.
_GLOBAL_RNG = threading.Lock()


def _fresh_rng_lock() -> None:
    """A forked child gets a lock of its own: one held by another thread at the fork would never
    be released there."""
    global _GLOBAL_RNG
    _GLOBAL_RNG = threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_fresh_rng_lock)

def hierarchy(A: sp.csr_matrix, x_nodes: NDArray[np.float64]) -> Any:
    """pyamg's smoothed-aggregation hierarchy of ``A``, the rigid-body modes of the nodes
    ``x_nodes`` as near-null space. pyamg estimates the spectral radius that smooths the
    prolongator from a random start (NumPy's global generator): seeded with :data:`AMG_SEED`, so
    that the same matrix gives the same hierarchy and a plan the same numbers run after run; the
    caller's generator state is put back."""
    import pyamg

    with _GLOBAL_RNG:
        state = np.random.get_state()
        np.random.seed(AMG_SEED)
        try:
            return pyamg.smoothed_aggregation_solver(
                A,
                B=rigid_modes(x_nodes),
                symmetry="symmetric",
                max_coarse=MAX_COARSE,
                coarse_solver="splu",
                presmoother=PRESMOOTHER,
                postsmoother=POSTSMOOTHER,
            )
        finally:
            np.random.set_state(state)
