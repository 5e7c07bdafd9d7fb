"""The kept multigrid hierarchy's coarse levels brought up to date with contacts
(:mod:`softgrasp.linalg.multigrid.coarse`): the Galerkin change against products formed whole, the lumped
change's rigid translations, the in-place level update against SciPy's sum and pyamg's block
inverses. (The kept hierarchy's convergence against a fresh one's: tests/test_linsolve.py.)"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from softgrasp.linalg.multigrid import coarse
from softgrasp.linalg.multigrid.coarse import UpdatedLevel, changed_nodes, galerkin_change


def _spring_stiffness(x: np.ndarray, pairs: np.ndarray, k: np.ndarray) -> sp.csr_matrix:
    """The stiffness of linear springs between nodes ``x`` (N, 3): each pair's 3 x 3 blocks
    k n n^T (symmetric; a rigid translation stretches none)."""
    rows, cols, vals = [], [], []
    for (i, j), kk in zip(pairs, k, strict=True):
        n = x[j] - x[i]
        n /= np.linalg.norm(n)
        B = kk * np.outer(n, n)
        for a, b, s in ((i, i, 1.0), (j, j, 1.0), (i, j, -1.0), (j, i, -1.0)):
            r, c = np.meshgrid(3 * a + np.arange(3), 3 * b + np.arange(3), indexing="ij")
            rows.append(r.ravel())
            cols.append(c.ravel())
            vals.append(s * B.ravel())
    N = x.shape[0]
    return sp.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(3 * N, 3 * N)
    )


def _springs(seed: int, N: int = 40):
    """A random spring network on ``N`` nodes (each joined to its 6 nearest), its stiffness made
    definite by a small diagonal; and a changed copy whose springs near node 0 got stiffer."""
    rng = np.random.default_rng(seed)
    x = rng.random((N, 3))
    d = np.linalg.norm(x[:, None] - x[None], axis=2)
    pairs = sorted({tuple(sorted((i, int(j)))) for i in range(N) for j in np.argsort(d[i])[1:7]})
    pairs = np.array(pairs)
    k = rng.uniform(1.0, 2.0, len(pairs))
    K0 = _spring_stiffness(x, pairs, k)
    A0 = (K0 + 1e-3 * sp.identity(3 * N)).tocsr()
    near = d[0, pairs].min(axis=1) < 0.35
    dA = _spring_stiffness(x, pairs[near], 0.5 * k[near])
    return A0, (A0 + dA).tocsr(), dA.tocsr(), x


def _prolongator(n: int, nc: int, seed: int) -> sp.csr_matrix:
    rng = np.random.default_rng(seed)
    P = sp.random(n, nc, density=0.3, random_state=rng, format="csr")
    return (P + sp.eye(n, nc)).tocsr()


def test_stiffened_nodes_leave_the_coarse_space():
    """With stiffened nodes only, the change is P'^T A0 P' - P^T A0 P, P' being P with those nodes'
    rows zeroed: the products formed whole (dense) agree to rounding."""
    A0, _, _, _ = _springs(1)
    n = A0.shape[0]
    P = _prolongator(n, 18, 2)
    stiffened = np.array([0, 3, 17])
    rows = (3 * stiffened[:, None] + np.arange(3)).ravel()
    Pm = P.toarray()
    Pm[rows] = 0.0
    want = Pm.T @ A0.toarray() @ Pm - P.toarray().T @ A0.toarray() @ P.toarray()
    got = galerkin_change(P, A0, A0, stiffened, np.zeros(0, dtype=np.intp)).toarray()
    assert np.abs(want).max() > 0
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * np.abs(want).max())


def test_the_change_of_every_node_is_the_galerkin_product_of_the_whole_change():
    """Every node changed (no coupling to an unchanged node to move): the change is P^T (A - A0) P."""
    A0, A, dA, _ = _springs(3)
    n = A0.shape[0]
    P = _prolongator(n, 15, 4)
    want = P.toarray().T @ dA.toarray() @ P.toarray()
    got = galerkin_change(P, A0, A, np.zeros(0, dtype=np.intp), np.arange(n // 3)).toarray()
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * np.abs(want).max())


def test_a_changed_patch_leaves_rigid_translations_free():
    """Stiffer springs around node 0, and only some of the nodes they join counted as changed: the
    change (with P the identity: the change on the finest level itself) is zero outside those
    nodes' rows and columns, equals A - A0 between two of them, and, as the springs' change, meets a
    rigid translation with no force; taking A - A0 in the patch's whole rows and columns instead
    (its edge cut through springs) would not."""
    A0, A, dA, _ = _springs(5)
    n = A0.shape[0]
    N = n // 3
    touched = np.unique(dA.tocoo().row // 3)
    changed = touched[::2]  # part of the patch: springs cross its edge
    I = sp.identity(n, format="csr")
    D = galerkin_change(I, A0, A, np.zeros(0, dtype=np.intp), changed).toarray()
    inside = np.zeros(N, dtype=bool)
    inside[changed] = True
    dofs = np.repeat(inside, 3)
    assert np.abs(D[~dofs]).max() == 0 and np.abs(D[:, ~dofs]).max() == 0
    full = dA.toarray()
    off = ~np.kron(np.eye(N, dtype=bool), np.ones((3, 3), dtype=bool))  # off the diagonal blocks
    both = np.outer(dofs, dofs) & off
    np.testing.assert_allclose(D[both], full[both], rtol=0, atol=1e-12 * np.abs(full).max())
    for axis in range(3):
        t = np.zeros(n)
        t[axis::3] = 1.0
        assert np.abs(full @ t).max() <= 1e-12 * np.abs(full).max()
        assert np.abs(D @ t).max() <= 1e-12 * np.abs(full).max()
        cut = np.where(np.outer(dofs, np.ones(n, bool)) | np.outer(np.ones(n, bool), dofs), full, 0.0)
        assert np.abs(cut @ t).max() > 1e-3 * np.abs(full).max()


@pytest.mark.parametrize("scale", [1.0, 3.0])
def test_changed_and_stiffened_nodes_from_the_diagonals(scale):
    """A node is stiffened when one of its diagonal entries grew past STIFFENED times the build
    value, changed when one moved by more than CHANGED of it (either way), both relative to the
    median node's ratio (here most nodes keep their stiffness, or all of it is scaled by three:
    the same nodes stand out); an entry not positive at the build counts as changed when it
    differs. A stiffness scaled throughout changes no node."""
    d0 = np.ones(300)
    d0[15] = 0.0
    d = d0.copy()
    d[0] = 2.0  # node 0 stiffened
    d[4] = 1.0 + 0.5 * coarse.CHANGED  # node 1: within CHANGED
    d[8] = 1.0 + 2.0 * coarse.CHANGED  # node 2 changed
    d[10] = 0.5  # node 3 softened: changed
    d[15] = 1e-9  # node 5: not positive at the build, now differs
    d = np.where(d0 > 0, scale * d, d)
    stiffened, changed = changed_nodes(d, d0)
    assert stiffened.tolist() == [0, 5]
    assert changed.tolist() == [0, 2, 3, 5]
    none = changed_nodes(5.0 * np.ones(300), np.ones(300))
    assert none[0].size == 0 and none[1].size == 0


def test_at_most_max_changed_nodes_the_largest_changes(monkeypatch):
    monkeypatch.setattr(coarse, "MAX_CHANGED", 3)
    d0 = np.ones(90)
    d = d0.copy()
    d[0:30:3] = 1.0 + np.array([0.1, 0.5, 0.2, 0.9, 0.3, 0.6, 0.07, 0.8, 0.4, 0.06])
    _, changed = changed_nodes(d, d0)
    assert changed.tolist() == [3, 5, 7]


def _bsr_level(seed: int, nb: int = 12, b: int = 6) -> sp.bsr_matrix:
    rng = np.random.default_rng(seed)
    S = sp.random(nb, nb, density=0.3, random_state=rng, format="csr")
    pattern = ((S + S.T) + sp.identity(nb)).tocsr()
    pattern.data[:] = 1.0
    dense = np.kron(pattern.toarray(), np.ones((b, b))) * rng.standard_normal((nb * b, nb * b))
    dense = dense + dense.T + np.kron(np.identity(nb), 10.0 * np.identity(b))
    M = sp.bsr_matrix(dense, blocksize=(b, b))
    M.sum_duplicates()
    return M


def test_an_updated_level_is_the_built_operator_plus_the_change_and_resets_to_its_bits():
    """The level's operator after ``update`` is the built one plus the change (SciPy's sum), its
    sweeps' diagonal inverses pyamg's of that operator; ``reset`` gives back the built values and
    inverses to the bit. A change with a block outside the pattern gives a new matrix, the built
    one untouched."""
    from pyamg.util.utils import get_block_diag

    from softgrasp.linalg.smoothers import BlockGaussSeidel

    built = _bsr_level(7)
    values = built.data.copy()
    before = built.toarray()
    sweeps = BlockGaussSeidel(built)
    inverses = sweeps.inverse_diagonal.copy()
    level = UpdatedLevel(built, sweeps)
    n = built.shape[0]
    rng = np.random.default_rng(8)
    dense = before * (rng.random((n, n)) < 0.05) * rng.standard_normal((n, n))
    dense[0, 0] += 3.0  # a diagonal block changed
    change = sp.csr_matrix(dense)
    level.update(change)
    want = before + change.toarray()
    np.testing.assert_allclose(level.matrix.toarray(), want, rtol=0, atol=1e-14 * np.abs(want).max())
    assert level.changed and level.sweeps is sweeps and level.matrix is built  # changed in place
    np.testing.assert_allclose(
        sweeps.inverse_diagonal,
        get_block_diag(sp.bsr_matrix(want, blocksize=(6, 6)), blocksize=6, inv_flag=True),
        rtol=0,
        atol=1e-10 * np.abs(inverses).max(),
    )
    level.update(2.0 * change)  # a second change replaces the first
    np.testing.assert_allclose(
        level.matrix.toarray(), before + 2.0 * dense, rtol=0, atol=1e-14 * np.abs(want).max()
    )
    for _ in range(2):
        level.reset()
        assert np.array_equal(built.data, values) and np.array_equal(sweeps.inverse_diagonal, inverses)
        assert not level.changed
    outside = sp.lil_matrix((n, n))
    empty = np.argwhere(built.toarray() == 0)[0]
    outside[empty[0], empty[1]] = 1.0
    level.update(outside.tocsr())
    assert level.matrix is not built and np.array_equal(built.data, values)
    np.testing.assert_allclose(level.matrix.toarray(), before + outside.toarray(), rtol=0, atol=0)
    assert isinstance(level.sweeps, BlockGaussSeidel) and level.sweeps is not sweeps
