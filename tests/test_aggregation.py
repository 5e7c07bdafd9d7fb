"""The smoothed-aggregation hierarchy built with the compiled finest Galerkin product
(:mod:`softgrasp.linalg.multigrid.aggregation`, :mod:`softgrasp.linalg.multigrid.galerkin`) against SciPy's product and
pyamg's own hierarchy."""

from __future__ import annotations

import platform

import numba
import numpy as np
import pytest
import scipy.sparse as sp

from softgrasp.physics.body import build_body
from softgrasp.model.material import preset
from softgrasp.model.mesh.generate import box
from softgrasp.linalg import solve as linsolve


def _cube(n: int):
    """The foam cube's rest stiffness on a table (its bottom nodes' penalty), slightly shifted, its
    mesh numbered for locality; the node positions."""
    body = build_body(box(0.05, n).reordered(), preset("foam"), mass=0.0125)
    K = (-body.rest_jacobian).tocsr()
    x = np.asarray(body.mesh.points)
    d = np.zeros(K.shape[0])
    for i in np.flatnonzero(x[:, 2] < x[:, 2].min() + 1e-9):
        d[3 * i : 3 * i + 3] = 0.5 * K.diagonal()[3 * i : 3 * i + 3]
    return (K + 1e-6 * sp.diags(K.diagonal()) + sp.diags(d)).tocsr(), x


def _pyamg(A, x):
    import pyamg

    np.random.seed(linsolve.AMG_SEED)
    return pyamg.smoothed_aggregation_solver(
        A,
        B=linsolve._rigid_modes(x),
        symmetry="symmetric",
        max_coarse=linsolve.MAX_COARSE,
        coarse_solver="splu",
        presmoother=linsolve._PRESMOOTHER,
        postsmoother=linsolve._POSTSMOOTHER,
    )


def test_the_compiled_galerkin_product_is_scipys_and_the_same_bits_on_one_thread_or_two():
    """``galerkin_product(A, P)`` against SciPy's ``P.T @ A @ P`` for the foam cube's matrix and its
    smoothed prolongator (1 x 6 blocks) and for a random unsymmetric matrix with a random
    prolongator: equal to rounding, canonical 6 x 6 blocks; on one thread and two the same bits;
    other block sizes refused."""
    from softgrasp.linalg.multigrid.galerkin import galerkin_product

    A, x = _cube(8)
    P = _pyamg(A, x).levels[0].P
    rng = np.random.default_rng(3)
    G = sp.random(A.shape[0], A.shape[0], density=0.01, random_state=rng, format="csr")
    Q = sp.random(A.shape[0], 60, density=0.05, random_state=rng, format="csr")
    cases = [(A, P), (G, sp.bsr_array(Q.toarray(), blocksize=(1, 6)))]
    for M, R in cases:
        want = (R.T @ M @ R).toarray()
        results = []
        for threads in (1, 2):
            before = numba.get_num_threads()
            numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
            try:
                C = galerkin_product(M, R)
            finally:
                numba.set_num_threads(before)
            assert C.format == "bsr" and tuple(C.blocksize) == (6, 6) and C.has_sorted_indices
            results.append(C)
        np.testing.assert_allclose(results[0].toarray(), want, rtol=0, atol=1e-13 * np.abs(want).max())
        assert np.array_equal(results[0].data, results[1].data)
    with pytest.raises(ValueError, match="1 x 6 blocks"):
        galerkin_product(A, sp.bsr_array(Q.toarray()[:, :54], blocksize=(1, 3)))


def test_the_hierarchy_is_pyamgs_with_its_finest_galerkin_product_compiled():
    """``smoothed_aggregation`` against pyamg's ``smoothed_aggregation_solver`` with the same
    options and seed: the finest level's prolongator the same to rounding (the same aggregates and
    candidates; the spectral radius by pyamg's Arnoldi process on softgrasp's products), the second
    level's operator the same to rounding; coarser
    levels are built from it by the same steps (its blocks in column order, where SciPy's product
    leaves them in the order it reached them: the aggregates may differ there). Multigrid CG with
    either hierarchy solves the system to 1e-8 in about the same number of V-cycles."""
    from softgrasp.linalg.multigrid.aggregation import smoothed_aggregation

    A, x = _cube(12)
    want = _pyamg(A, x)
    np.random.seed(linsolve.AMG_SEED)
    got = smoothed_aggregation(
        A,
        linsolve._rigid_modes(x),
        linsolve.MAX_COARSE,
        "splu",
        linsolve._PRESMOOTHER,
        linsolve._POSTSMOOTHER,
    )
    assert len(got.levels) == len(want.levels) == 3
    P, W = got.levels[0].P, want.levels[0].P
    assert P.format == W.format == "bsr" and tuple(P.blocksize) == tuple(W.blocksize)
    assert np.array_equal(P.indptr, W.indptr) and np.array_equal(P.indices, W.indices)
    assert abs(P - W).max() <= 1e-14 * abs(W).max()
    A1, W1 = got.levels[1].A, want.levels[1].A
    assert abs(A1 - W1).max() <= 1e-13 * abs(W1).max()
    b = np.random.default_rng(5).standard_normal(A.shape[0])
    counts = []
    for ml in (got, want):
        residuals: list[float] = []
        ml.solve(b, tol=1e-8, accel="cg", residuals=residuals)
        assert residuals[-1] <= 1e-8 * residuals[0]
        counts.append(len(residuals))
    assert abs(counts[0] - counts[1]) <= 2, counts


def _same_bits_here(got, want):
    """The same bits on x86-64, where neither pyamg's C++ nor Numba fuses multiply-adds; within a
    few units in the last place elsewhere (arm64 compilers fuse them by default)."""
    if platform.machine().lower() in ("x86_64", "amd64"):
        assert np.array_equal(got, want)
    else:
        np.testing.assert_allclose(got, want, rtol=1e-13, atol=1e-300)


def test_the_candidates_sweeps_are_pyamgs_to_the_bit():
    """The finest candidates' four symmetric Gauss-Seidel sweeps on ``A x = 0``, all columns in
    one pass over each row (:func:`softgrasp.linalg.multigrid.candidates.gauss_seidel_columns`), against
    pyamg's relaxation operator applied column by column: the same bits for the six rigid-body
    modes on the cube, and for six random columns on a matrix whose rows hold their columns out
    of order, with duplicate entries (one on a diagonal) and 64-bit indices, one row without its
    diagonal and one with a stored zero there (pyamg leaves both alone)."""
    from pyamg.relaxation.utils import relaxation_as_linear_operator

    from softgrasp.linalg.multigrid.aggregation import IMPROVE_CANDIDATES, _improved_candidates, _sweeps_compiled

    assert _sweeps_compiled(IMPROVE_CANDIDATES)
    assert not _sweeps_compiled(("block_gauss_seidel", {"sweep": "forward", "iterations": 4}))
    assert not _sweeps_compiled(("jacobi", {"iterations": 4}))
    A, x = _cube(8)
    B = linsolve._rigid_modes(x)
    zero = np.zeros((A.shape[0], 1))
    want = relaxation_as_linear_operator(IMPROVE_CANDIDATES, A, zero) @ B
    got = _improved_candidates(A, B)
    _same_bits_here(got, want)
    assert not np.array_equal(got, B)  # the sweeps changed the candidates
    assert np.array_equal(B, linsolve._rigid_modes(x))  # and left the input alone

    rng = np.random.default_rng(3)
    M = A.tolil()
    M[7, 7] = 0.0
    M = M.tocsr()
    M.eliminate_zeros()
    data, indices, indptr = M.data.copy(), M.indices.astype(np.int64), M.indptr.astype(np.int64)
    for i in range(M.shape[0]):  # each row's entries in a random order
        lo, hi = indptr[i], indptr[i + 1]
        order = lo + rng.permutation(hi - lo)
        data[lo:hi], indices[lo:hi] = data[order], indices[order]
    # Row 11 gets its diagonal and one off-diagonal entry twice (summed by pyamg's loop as stored,
    # its last diagonal entry taken); row 12 a stored zero on its diagonal.
    rows = [(indices[indptr[i] : indptr[i + 1]], data[indptr[i] : indptr[i + 1]]) for i in range(M.shape[0])]
    c11, d11 = rows[11]
    k = int(np.flatnonzero(c11 == 11)[0])
    other = int(np.flatnonzero(c11 != 11)[0])
    rows[11] = (
        np.concatenate([c11, [11, c11[other]]]),
        np.concatenate([d11, [0.5 * d11[k], 0.25 * d11[other]]]),
    )
    c12, d12 = rows[12]
    rows[12] = (c12, np.where(c12 == 12, 0.0, d12))
    indptr = np.concatenate([[0], np.cumsum([len(c) for c, _ in rows])]).astype(np.int64)
    M = sp.csr_matrix(
        (np.concatenate([d for _, d in rows]), np.concatenate([c for c, _ in rows]), indptr), shape=M.shape
    )
    M.indices, M.indptr = M.indices.astype(np.int64), M.indptr.astype(np.int64)
    assert not M.has_sorted_indices and M.indices.dtype == np.int64
    B3 = rng.standard_normal((M.shape[0], 6))
    got = _improved_candidates(M, B3)
    want = relaxation_as_linear_operator(IMPROVE_CANDIDATES, M, zero) @ B3
    _same_bits_here(got, want)
    assert np.array_equal(got[7], B3[7]) and np.array_equal(got[12], B3[12])
    from softgrasp.linalg.multigrid.candidates import gauss_seidel_columns

    with pytest.raises(ValueError, match="six float64 columns"):
        gauss_seidel_columns(M.indptr, M.indices, M.data, np.zeros((M.shape[0], 3)), 1)
    with pytest.raises(ValueError, match="must match"):
        gauss_seidel_columns(M.indptr, M.indices, M.data, np.zeros((M.shape[0] - 1, 6)), 1)
    assert not np.array_equal(got[11], B3[11])


def test_the_spectral_radius_is_pyamgs_estimate_to_rounding(monkeypatch):
    """The spectral radius of D^-1 A that weights the prolongator's smoothing, estimated by pyamg's
    restarted Arnoldi process on softgrasp's compiled products (node blocks on the finest level,
    6 x 6 blocks on the next): pyamg's estimate to rounding from the same seed, and the same draws
    consumed from NumPy's generator; restarted (to 1e-8), also where the dominant Ritz values are
    complex; and, for a diagonal matrix, within 1 % below its largest entry."""
    from pyamg.util.linalg import approximate_spectral_radius
    from pyamg.util.utils import get_diagonal, scale_rows

    from softgrasp.linalg.multigrid import aggregation
    from softgrasp.linalg.multigrid.aggregation import _spectral_radius

    A, x = _cube(8)
    np.random.seed(linsolve.AMG_SEED)
    ml = _pyamg(A, x)
    for M in (A, ml.levels[1].A):
        D_inv = get_diagonal(M, inv=True)
        np.random.seed(11)
        want = approximate_spectral_radius(scale_rows(M, D_inv, copy=True))
        after_want = np.random.rand()
        np.random.seed(11)
        got = _spectral_radius(M, np.asarray(D_inv, dtype=np.float64))
        assert np.random.rand() == after_want
        assert got == pytest.approx(want, rel=1e-13)
    # Restarted: the cube's matrix to 1e-8 (several runs), and a scaled Poisson matrix S P S whose
    # D^-1 A is far from normal, so that the dominant Ritz values are complex and the restarts run
    # in complex arithmetic as pyamg's do.
    n = 60
    poisson = sp.diags([-np.ones(n - 1), 2 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1])
    S = sp.diags(np.exp(np.random.default_rng(1).uniform(0.0, np.log(1e3), n)))
    for M in (A, (S @ poisson @ S).tocsr()):
        D_inv = get_diagonal(M, inv=True)
        np.random.seed(5)
        want = approximate_spectral_radius(scale_rows(M, D_inv, copy=True), tol=1e-8)
        monkeypatch.setattr(aggregation, "RHO_TOL", 1e-8)
        np.random.seed(5)
        got = _spectral_radius(M, np.asarray(D_inv, dtype=np.float64))
        monkeypatch.undo()
        assert got == pytest.approx(want, rel=1e-12)
    # A diagonal D^-1 A (30 eigenvalues, 15 Arnoldi steps): the estimate is a Ritz value of a
    # symmetric matrix, so no larger than its largest eigenvalue, and within the 1 % of it that
    # ends the process.
    lam = np.linspace(1.0, 4.0, 30) * np.linspace(2.0, 1.0, 30)
    np.random.seed(11)
    rho = _spectral_radius(sp.diags(lam).tocsr(), np.full(30, 0.5))
    assert 0.99 * 0.5 * lam.max() <= rho <= 0.5 * lam.max() * (1 + 1e-12)
