"""The multigrid path's compiled sparse kernels (products, l1 hybrid Gauss-Seidel sweeps) and the
V-cycle softgrasp applies with them, against SciPy, pyamg and the properties conjugate gradients
need."""

from __future__ import annotations

import numba
import numpy as np
import pytest
import scipy.sparse as sp

from oracles import without_parallel_kernels
from softgrasp.linalg.multigrid import hierarchy
from softgrasp.linalg.multigrid import krylov as mg_krylov
from softgrasp.linalg.solve import SolverCache
from softgrasp.model.material import preset
from softgrasp.model.mesh.generate import box
from softgrasp.physics.body import build_body


def _cube_system(n: int = 6, local: bool = False):
    """The foam cube's rest stiffness, held on a table (its bottom nodes' penalty) and slightly
    shifted: a symmetric positive definite Newton matrix; the node positions. ``local``: the
    mesh renumbered for locality (as softgrasp's gmsh meshes are)."""
    mesh = box(0.05, n)
    body = build_body(mesh.reordered() if local else mesh, preset("foam"), mass=0.0125)
    K = (-body.rest_jacobian).tocsr()
    x = np.asarray(body.mesh.points)
    d = np.zeros(K.shape[0])
    bottom = np.flatnonzero(x[:, 2] < x[:, 2].min() + 1e-9)
    for i in bottom:
        d[3 * i : 3 * i + 3] = 0.5 * K.diagonal()[3 * i : 3 * i + 3]
    A = (K + 1e-6 * sp.diags(K.diagonal()) + sp.diags(d)).tocsr()
    return A, x


def test_the_compiled_product_is_scipys_and_the_same_bits_on_one_thread_or_two():
    from softgrasp.linalg.sparse import CsrProduct

    A, _ = _cube_system()
    v = np.random.default_rng(0).standard_normal(A.shape[0])
    want = A @ v
    before = numba.get_num_threads()
    op = CsrProduct(A, threads=1)
    one = op @ v
    op.threads = 2
    two = op @ v
    np.testing.assert_allclose(one, want, rtol=0, atol=1e-13 * np.abs(want).max())
    assert np.array_equal(one, two)
    assert numba.get_num_threads() == before  # put back
    with pytest.raises(ValueError, match="times a vector"):
        op @ v[:-1]


def test_a_hybrid_sweep_on_a_matrix_without_couplings_between_blocks_is_gauss_seidel():
    """With no coupling between the row blocks the l1 term vanishes and the hybrid sweep is
    Gauss-Seidel itself: pyamg's forward and backward sweeps, to rounding."""
    from pyamg.relaxation.relaxation import gauss_seidel

    from softgrasp.linalg.smoothers import SWEEP_PARTS, HybridGaussSeidel

    A, _ = _cube_system(4)
    n = A.shape[0]
    # row i's block p: p n // parts <= i < (p + 1) n // parts
    part = np.searchsorted([p * n // SWEEP_PARTS for p in range(1, SWEEP_PARTS)], np.arange(n), side="right")
    coo = A.tocoo()
    keep = part[coo.row] == part[coo.col]
    B = sp.csr_matrix((coo.data[keep], (coo.row[keep], coo.col[keep])), shape=A.shape)
    assert (A - B).nnz > 0  # the cube's matrix did couple the blocks
    b = np.random.default_rng(1).standard_normal(n)
    for forward, sweep in ((True, "forward"), (False, "backward")):
        x0 = np.random.default_rng(2).standard_normal(n)
        want = x0.copy()
        gauss_seidel(B, want, b, iterations=1, sweep=sweep)
        got = x0.copy()
        HybridGaussSeidel(B, threads=2).sweep(got, b, forward=forward)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * np.abs(want).max())


def _forward_hybrid_matrix(A: np.ndarray, parts: int, l1: bool) -> np.ndarray:
    """M of the forward hybrid sweep x <- x + M^-1 (b - A x), from its definition: the lower
    triangle (diagonal included) within each row block, plus the l1 term on the diagonal."""
    n = len(A)
    block = np.searchsorted([p * n // parts for p in range(1, parts)], np.arange(n), side="right")
    same = block[:, None] == block[None, :]
    M = np.tril(np.where(same, A, 0.0))
    if l1:
        M += np.diag(np.where(same, 0.0, np.abs(A)).sum(axis=1))
    return M


def test_l1_hybrid_sweeps_converge_where_plain_hybrid_ones_diverge():
    """A symmetric positive definite 6 x 6 matrix (rank two plus 0.05 I) on which Gauss-Seidel
    within two row blocks and Jacobi across them diverges (the iteration matrix's spectral radius
    1.085); with each row's couplings to the other block added to its diagonal (the l1 term),
    M + M^T - A is positive definite and the compiled sweeps converge to A^-1 b, the error's
    energy norm falling at every sweep, forward and backward."""
    from softgrasp.linalg.smoothers import SWEEP_PARTS, HybridGaussSeidel

    B = np.array([[-0.7, -0.1], [0.8, 1.5], [-1.3, 1.5], [1.3, 0.8], [0.3, -0.3], [1.5, 2.0]])
    A = B @ B.T + 0.05 * np.eye(6)
    assert np.linalg.eigvalsh(A).min() > 0
    plain = _forward_hybrid_matrix(A, SWEEP_PARTS, l1=False)
    l1 = _forward_hybrid_matrix(A, SWEEP_PARTS, l1=True)
    assert np.abs(np.linalg.eigvals(np.eye(6) - np.linalg.solve(plain, A))).max() > 1.05
    assert np.linalg.eigvalsh(l1 + l1.T - A).min() > 0

    b = np.random.default_rng(3).standard_normal(6)
    exact = np.linalg.solve(A, b)
    gs = HybridGaussSeidel(sp.csr_matrix(A), threads=2, parts=SWEEP_PARTS)
    np.testing.assert_allclose(gs.inverse_diagonal, 1.0 / np.diag(l1), rtol=1e-14)
    x = np.zeros(6)
    errors = [float((x - exact) @ A @ (x - exact))]
    for k in range(3000):
        gs.sweep(x, b, forward=k % 2 == 0)
        errors.append(float((x - exact) @ A @ (x - exact)))
    assert all(e1 < e0 for e0, e1 in zip(errors[:1000], errors[1:1001], strict=True)), errors[:10]
    assert errors[-1] <= 1e-10 * errors[0]  # slowly: the l1 iteration's spectral radius is 0.995
    # One forward sweep is x + M^-1 (b - A x) with M as defined above.
    x0 = np.random.default_rng(4).standard_normal(6)
    got = x0.copy()
    gs.sweep(got, b, forward=True)
    np.testing.assert_allclose(got, x0 + np.linalg.solve(l1, b - A @ x0), rtol=1e-12)


def test_the_v_cycle_is_symmetric_and_the_same_bits_on_one_thread_or_two():
    """Conjugate gradients need a symmetric preconditioner: u . M v = v . M u for the V-cycle
    (l1 hybrid sweeps forward before the coarse correction, backward after); and the same
    hierarchy and cycle, to the bit, whatever the thread count and from one build to the next
    (pyamg's random start seeded, the caller's generator left as it was)."""
    from softgrasp.linalg.smoothers import BlockGaussSeidel, HybridBlockGaussSeidel

    A, x_nodes = _cube_system(12, local=True)
    rng = np.random.default_rng(5)
    u, v = rng.standard_normal((2, A.shape[0]))
    np.random.seed(7)
    np.random.random(3)
    state = np.random.get_state()
    M = mg_krylov.multigrid(A, x_nodes, SolverCache(method="amg"))
    after = np.random.get_state()
    assert np.array_equal(after[1], state[1]) and after[2:] == state[2:]
    assert len(M.ml.levels) == 3 and M._sweeps[0].parts == 2  # the coarse recursion, two blocks
    assert isinstance(M._sweeps[1], BlockGaussSeidel)  # the second level's 6 x 6 block sweeps
    assert isinstance(M._sweeps[0], HybridBlockGaussSeidel)  # the finest level's by node blocks
    Mu, Mv = M @ u, M @ v
    assert abs(u @ Mv - v @ Mu) <= 1e-12 * np.linalg.norm(u) * np.linalg.norm(Mv)
    results = []
    for threads in (1, 2):
        other = mg_krylov.multigrid(A, x_nodes, SolverCache(method="amg"))
        other.use(A, threads)
        results.append(other @ u)
    assert np.array_equal(results[0], results[1]) and np.array_equal(results[0], Mu)


def test_the_v_cycle_with_pyamgs_smoothers_is_pyamgs_own():
    """Where the parallel kernels cannot run (a forked child whose Numba threads were lost,
    :func:`softgrasp.backend.compiled` false) the cycle keeps pyamg's Gauss-Seidel on every level: it is then
    pyamg's own V-cycle (its preconditioner), to the rounding of the products, on a three-level
    hierarchy built while the compiled kernels were in use and kept for the next matrix (no
    compiled sweep of the earlier matrix left behind)."""
    A, x_nodes = _cube_system(12, local=True)
    A2 = (A + 0.5 * sp.diags(A.diagonal())).tocsr()
    r = np.random.default_rng(6).standard_normal(A.shape[0])
    cache = SolverCache(method="amg")
    mg_krylov.multigrid(A, x_nodes, cache)
    with without_parallel_kernels():
        M = mg_krylov.multigrid(A2, x_nodes, cache)
        got = M @ r
    assert len(M.ml.levels) == 3 and M.ml.levels[0].A is A2
    # pyamg's own cycle on the same (seeded) hierarchy, its finest level swapped as softgrasp's
    reference = hierarchy.hierarchy(A, x_nodes)
    reference.levels[0].A = A2
    want = reference.aspreconditioner(cycle="V").matvec(r)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * np.abs(want).max())


def test_a_matrix_not_numbered_for_locality_is_swept_as_one_block():
    """The box as meshed (its BCC lattice's corner nodes first, then the centres: most entries
    couple the two halves) is swept as one block: Gauss-Seidel, pyamg's sweep to rounding; the
    same box renumbered for locality is swept in two."""
    from pyamg.relaxation.relaxation import gauss_seidel

    from softgrasp.linalg.smoothers import SWEEP_PARTS, HybridGaussSeidel

    A, _ = _cube_system(8)
    sweeps = HybridGaussSeidel(A, threads=2)
    assert sweeps.parts == 1
    b = np.random.default_rng(8).standard_normal(A.shape[0])
    x0 = np.random.default_rng(9).standard_normal(A.shape[0])
    want = x0.copy()
    gauss_seidel(A, want, b, iterations=1, sweep="forward")
    got = x0.copy()
    sweeps.sweep(got, b, forward=True)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * np.abs(want).max())
    assert HybridGaussSeidel(_cube_system(8, local=True)[0]).parts == SWEEP_PARTS


def _random_bsr(rows: int, cols: int, blocksize: tuple[int, int], seed: int) -> sp.bsr_matrix:
    """A random BSR matrix of ``rows`` x ``cols`` blocks (about a fifth of them present)."""
    rng = np.random.default_rng(seed)
    r, c = blocksize
    pattern = sp.random(rows, cols, density=0.2, random_state=seed, format="csr")
    pattern.data[:] = 1.0
    blocks = sp.kron(pattern, np.ones((r, c)), format="csr")
    blocks.data = rng.standard_normal(blocks.nnz)
    return blocks.tobsr(blocksize=blocksize)


@pytest.mark.parametrize("blocksize", [(6, 6), (6, 1), (1, 6)])
def test_the_block_products_are_scipys_and_the_same_bits_on_one_thread_or_two(blocksize):
    """The BSR products of the multigrid hierarchy's block shapes against SciPy's product, and
    the same to the bit on one thread or two; other shapes and formats get the CSR product."""
    from softgrasp.linalg.sparse import BsrProduct, CsrProduct, product

    A = _random_bsr(40, 30, blocksize, seed=sum(blocksize))
    x = np.random.default_rng(11).standard_normal(A.shape[1])
    op = product(A)
    assert isinstance(op, BsrProduct)
    want = A @ x
    got = []
    for threads in (1, 2):
        op.threads = threads
        got.append(op @ x)
    np.testing.assert_allclose(got[0], want, rtol=0, atol=1e-13 * np.abs(want).max())
    assert np.array_equal(got[0], got[1])
    assert isinstance(product(A.tocsr()), CsrProduct)
    assert isinstance(product(_random_bsr(10, 10, (3, 3), seed=1)), CsrProduct)
    with pytest.raises(ValueError, match="a block product needs"):
        BsrProduct(_random_bsr(10, 10, (3, 3), seed=1))
    with pytest.raises(ValueError, match="times a vector of shape"):
        op @ np.ones(A.shape[1] + 1)


def test_the_block_sweeps_are_pyamgs_block_gauss_seidel_and_converge():
    """A forward and a backward sweep of the 6 x 6 block Gauss-Seidel against pyamg's
    ``block_gauss_seidel`` (to round-off); repeated symmetric sweeps on a symmetric positive
    definite matrix reduce the error's energy norm every time (block Gauss-Seidel converges for
    such matrices) to the solution of the system solved directly."""
    from pyamg.relaxation.relaxation import block_gauss_seidel

    from softgrasp.linalg.smoothers import BlockGaussSeidel

    rng = np.random.default_rng(12)
    G = _random_bsr(25, 25, (6, 6), seed=3).tocsr()
    A = (G @ G.T + 5.0 * sp.eye(G.shape[0])).tobsr(blocksize=(6, 6))
    b = rng.standard_normal(A.shape[0])
    x0 = rng.standard_normal(A.shape[0])
    sweeps = BlockGaussSeidel(A)
    for forward in (True, False):
        want = x0.copy()
        block_gauss_seidel(A, want, b, iterations=1, sweep="forward" if forward else "backward", blocksize=6)
        got = x0.copy()
        sweeps.sweep(got, b, forward=forward)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * np.abs(want).max())
    exact = sp.linalg.spsolve(A.tocsc(), b)
    x = np.zeros_like(b)
    errors = [float((x - exact) @ (A @ (x - exact)))]
    for k in range(400):
        sweeps.sweep(x, b, forward=k % 2 == 0)
        errors.append(float((x - exact) @ (A @ (x - exact))))
    assert all(e1 < e0 for e0, e1 in zip(errors[:100], errors[1:101], strict=True)), errors[:5]
    assert errors[-1] <= 1e-20 * errors[0]
    with pytest.raises(ValueError, match="6 x 6 blocks"):
        BlockGaussSeidel(A.tocsr())
    with pytest.raises(ValueError, match="contiguous float64"):
        sweeps.sweep(np.zeros(A.shape[0], dtype=np.float32), b, forward=True)


def _block_hybrid_matrix(A: np.ndarray, parts: int, forward: bool) -> np.ndarray:
    """M of one node-block hybrid sweep x <- x + M^-1 (b - A x), from its definition: the 3 x 3
    block lower (forward) or upper (backward) triangle, diagonal blocks included, within each part
    of the block rows, plus each row's l1 term (its entries' |a| in the other parts' blocks) on the
    diagonal."""
    n = len(A)
    nb = n // 3
    part = np.searchsorted([p * nb // parts for p in range(1, parts)], np.arange(nb), side="right")
    node = np.arange(n) // 3
    same = part[node][:, None] == part[node][None, :]
    order = node[:, None] >= node[None, :] if forward else node[:, None] <= node[None, :]
    M = np.where(same & order, A, 0.0)
    return M + np.diag(np.where(same, 0.0, np.abs(A)).sum(axis=1))


def test_node_block_sweeps_and_products_are_their_definition_and_the_same_bits_on_one_thread_or_two():
    """A body's Newton matrix (the foam cube on its table, numbered for locality; SciPy's sums
    dropped the exact zeros of its axis-aligned springs) is read as 3 x 3 node blocks: the blocks
    are SciPy's own BSR conversion, the product is SciPy's, and a forward
    or backward sweep is x + M^-1 (b - A x) with M the block hybrid splitting plus the l1 term,
    solved densely; the same bits on one thread or two; repeated symmetric sweeps converge (the
    l1 term keeps M + M^T - A positive definite). A matrix that is not made of full node blocks
    keeps the row-wise sweeps."""
    from softgrasp.linalg.smoothers import (
        SWEEP_PARTS,
        HybridBlockGaussSeidel,
        HybridGaussSeidel,
        fine_smoother,
    )
    from softgrasp.linalg.sparse import node_blocks

    A, _ = _cube_system(5, local=True)
    blocks = node_blocks(A)
    assert blocks is not None
    want = A.tobsr(blocksize=(3, 3))
    want.sort_indices()
    assert np.array_equal(blocks[0], want.indptr) and np.array_equal(blocks[1], want.indices)
    assert np.array_equal(blocks[2], want.data)
    assert isinstance(fine_smoother(A, threads=2), HybridBlockGaussSeidel)
    gs = HybridBlockGaussSeidel(A, blocks, threads=2, parts=SWEEP_PARTS)
    assert gs.parts == HybridGaussSeidel(A).parts  # the same choice of parts by default
    rng = np.random.default_rng(13)
    b, x0 = rng.standard_normal((2, A.shape[0]))
    np.testing.assert_allclose(gs @ x0, A @ x0, rtol=0, atol=1e-13 * np.abs(A @ x0).max())
    dense = A.toarray()
    for forward in (True, False):
        want = x0 + np.linalg.solve(_block_hybrid_matrix(dense, SWEEP_PARTS, forward), b - dense @ x0)
        got = []
        for threads in (1, 2):
            gs.threads = threads
            x = x0.copy()
            gs.sweep(x, b, forward=forward)
            got.append(x)
        np.testing.assert_allclose(got[0], want, rtol=0, atol=1e-11 * np.abs(want).max())
        assert np.array_equal(got[0], got[1])
    exact = np.linalg.solve(dense, b)
    x = np.zeros_like(b)
    errors = [float((x - exact) @ dense @ (x - exact))]
    for k in range(60):
        gs.sweep(x, b, forward=k % 2 == 0)
        errors.append(float((x - exact) @ dense @ (x - exact)))
    assert all(e1 < e0 for e0, e1 in zip(errors[:-1], errors[1:], strict=True)), errors[:5]
    # A matrix of unknowns not in threes, or storing a sparse part of its node blocks (a
    # diagonal), keeps the row-wise sweeps.
    assert node_blocks(sp.eye(10, format="csr")) is None
    assert node_blocks(sp.eye(9, format="csr")) is not None
    assert type(fine_smoother(sp.eye(9, format="csr"))) is HybridGaussSeidel
    with pytest.raises(ValueError, match="contiguous float64"):
        gs.sweep(np.zeros(A.shape[0], dtype=np.float32), b, forward=True)


def test_unique_pairs_is_numpys_unique_and_the_block_pattern_the_numpy_oracles():
    """The compiled distinct node pairs (a counting sort) against ``np.unique`` of the pair keys,
    duplicates and empty rows included, and the body's Jacobian pattern built with either; bad
    input is refused."""
    from oracles.forces import block_pattern_arrays
    from softgrasp.linalg.sparse import block_layout, unique_pairs
    from softgrasp.physics.forces import BlockPattern, assemble_blocks
    from softgrasp.physics.springs import spring_pairs
    from softgrasp.physics.volume import volume_pairs

    rng = np.random.default_rng(14)
    for n, k in ((1, 5), (7, 0), (40, 3000)):
        rows, cols = rng.integers(0, n, k), rng.integers(0, n, k)
        r, c, inv = unique_pairs(rows, cols, n)
        keys, want_inv = np.unique(rows * n + cols, return_inverse=True)
        assert np.array_equal(r * n + c, keys) and np.array_equal(inv, want_inv)
    mesh = box(0.05, 4)
    body = build_body(mesh, preset("foam"), mass=0.0125)
    rows, cols = spring_pairs(body.edges)
    vr, vc = volume_pairs(body.mesh.tets)
    rows, cols = np.concatenate([rows, vr]), np.concatenate([cols, vc])
    # The body's pattern, and random pairs with repeats and empty block rows (the compiled layout,
    # kernels.sparse.block_layout, against NumPy's): the same arrays, types and matrix.
    cases = [(body.n_nodes, rows, cols), (40, rng.integers(0, 30, 900), rng.integers(0, 40, 900))]
    for n, r, c in cases:
        pattern = BlockPattern(n, r, c)
        base, stride, nnz, indptr, indices = block_pattern_arrays(n, r, c)
        oracle = {"block_base": base, "block_stride": stride, "indptr": indptr, "indices": indices}
        for attr in ("block_base", "block_stride", "indptr", "indices"):
            got, want = getattr(pattern, attr), oracle[attr]
            assert got.dtype == want.dtype and np.array_equal(got, want), attr
        assert pattern.nnz == nnz
        patterns = {"numba": pattern}
        blocks = rng.standard_normal((len(r), 3, 3))
        want = assemble_blocks(n, r, c, blocks).toarray()
        np.testing.assert_allclose(patterns["numba"].assemble(blocks).toarray(), want, rtol=1e-14, atol=1e-14)
    with pytest.raises(ValueError, match="sorted"):
        block_layout(np.array([1, 0]), np.array([0, 0]), np.array([0, 1]), 2, np.int32)
    with pytest.raises(ValueError, match="name one of"):
        block_layout(np.array([0, 1]), np.array([0, 0]), np.array([0, 2]), 2, np.int32)
    with pytest.raises(ValueError, match="columns must lie"):
        block_layout(np.array([0, 1]), np.array([0, 2]), np.array([0, 1]), 2, np.int32)
    with pytest.raises(ValueError, match="must lie in"):
        unique_pairs(np.array([0, 5]), np.array([1, 1]), 5)
    with pytest.raises(ValueError, match="equal-length"):
        unique_pairs(np.array([0, 1]), np.array([1]), 5)


def test_a_node_block_that_is_not_positive_definite_is_left_alone():
    """As the row-wise sweep leaves a row whose l1 diagonal is not positive, the node-block sweep
    leaves a node whose (l1) diagonal block is not positive definite: its unknowns unchanged, the
    others updated."""
    from softgrasp.linalg.smoothers import HybridBlockGaussSeidel
    from softgrasp.linalg.sparse import node_blocks

    D = np.diag([2.0, 2.0, 2.0, -1.0, -1.0, -1.0, 3.0, 3.0, 3.0])
    D[0, 1] = D[1, 0] = 0.5
    A = sp.csr_matrix(D)
    gs = HybridBlockGaussSeidel(A, node_blocks(A), parts=1)
    np.testing.assert_array_equal(gs.inverse_diagonal[1], np.zeros((3, 3)))
    x = np.zeros(9)
    b = np.ones(9)
    gs.sweep(x, b, forward=True)
    np.testing.assert_allclose(x[:3], np.linalg.solve(D[:3, :3], b[:3]), rtol=1e-14)
    np.testing.assert_array_equal(x[3:6], 0.0)
    np.testing.assert_allclose(x[6:], 1.0 / 3.0, rtol=1e-14)


def test_the_compiled_diagonal_is_scipys_with_duplicates_and_unsorted_indices():
    """``kernels.sparse.diagonal`` and the finest level's sweeps' ``diagonal()`` (the multigrid path
    reads each Newton matrix's diagonal to find the nodes contacts stiffened) against SciPy's
    ``diagonal()``: duplicate entries summed, each row's entries in reverse order, rows without a
    diagonal entry 0."""
    from softgrasp.linalg.smoothers import HybridBlockGaussSeidel, HybridGaussSeidel, fine_smoother
    from softgrasp.linalg.sparse import diagonal

    A, _ = _cube_system(5)
    assert np.array_equal(diagonal(A), A.diagonal())
    by_blocks = fine_smoother(A)  # the finest level's sweeps read it from their node blocks
    assert isinstance(by_blocks, HybridBlockGaussSeidel)
    assert np.array_equal(by_blocks.diagonal(), A.diagonal())
    assert np.array_equal(HybridGaussSeidel(A).diagonal(), A.diagonal())
    rng = np.random.default_rng(31)
    B = sp.random(60, 60, density=0.1, random_state=rng, format="csr")
    indptr, indices, data = [0], [], []
    for i in range(60):
        cols = list(B.indices[B.indptr[i] : B.indptr[i + 1]][::-1])
        vals = list(B.data[B.indptr[i] : B.indptr[i + 1]][::-1])
        if i % 3 == 0:  # a duplicate diagonal entry, first in the row
            cols, vals = [i, *cols], [0.25 * i, *vals]
        indices += cols
        data += vals
        indptr.append(len(indices))
    C = sp.csr_matrix((np.array(data), np.array(indices, dtype=np.int32), np.array(indptr)), shape=(60, 60))
    assert not C.has_sorted_indices
    want = C.toarray().diagonal()
    assert (want == 0).any() and (want[::3] != B.diagonal()[::3]).any()
    np.testing.assert_allclose(diagonal(C), want, rtol=1e-15, atol=0)


def test_block_sweeps_with_some_diagonal_blocks_changed_in_place():
    """A 6 x 6 block Gauss-Seidel whose matrix's values are changed in place (the multigrid's kept
    coarse levels, brought up to date): after ``invert_rows`` for the changed block rows its
    inverses are pyamg's of the new matrix, and its sweep pyamg's on it."""
    from pyamg.relaxation.relaxation import block_gauss_seidel
    from pyamg.util.utils import get_block_diag

    from softgrasp.linalg.smoothers import BlockGaussSeidel

    G = _random_bsr(20, 20, (6, 6), seed=5).tocsr()
    A = (G @ G.T + 5.0 * sp.eye(G.shape[0])).tobsr(blocksize=(6, 6))
    A.sum_duplicates()
    sweeps = BlockGaussSeidel(A)
    for r in (3, 11):
        lo, hi = A.indptr[r], A.indptr[r + 1]
        at = lo + np.flatnonzero(A.indices[lo:hi] == r)[0]
        A.data[at] += 2.0 * np.eye(6) + 0.1
    sweeps.invert_rows(np.array([11, 3, 3]))
    # A fresh copy of the changed matrix: pyamg keeps the inverses it computed on the matrix itself
    # (the very array the sweeps hold), and would hand them back.
    fresh = sp.bsr_matrix(A.toarray(), blocksize=(6, 6))
    inverses = get_block_diag(fresh, blocksize=6, inv_flag=True)
    assert not np.shares_memory(inverses, sweeps.inverse_diagonal)
    np.testing.assert_allclose(sweeps.inverse_diagonal, inverses, rtol=0, atol=1e-12)
    rng = np.random.default_rng(4)
    b, x0 = rng.standard_normal(A.shape[0]), rng.standard_normal(A.shape[0])
    want = x0.copy()
    block_gauss_seidel(fresh, want, b, iterations=1, sweep="forward", blocksize=6)
    got = x0.copy()
    sweeps.sweep(got, b, forward=True)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * np.abs(want).max())
