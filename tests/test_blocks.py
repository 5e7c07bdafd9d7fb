"""The block kernels (:mod:`softgrasp.sim.fused.blocks`: eight springs or tets a time in vector
instructions) against the fused stepper's scalar loops (:func:`softgrasp.sim.fused.step._edge_pass`,
``_tet_pass``) element block by element block: forces, energies, inverted masks, on blocks that
repeat a node (read-modify-writes in order), on a nearly and a fully inverted tet (the barrier's
floor), on a non-finite position; and the parameter layout of :func:`block_params`."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("numba")
import numba  # noqa: E402

from softgrasp.sim.fused import blocks, step  # noqa: E402
from softgrasp.physics.forces_compiled import _J_FLOOR  # noqa: E402

A2, A3 = 0.4, 2.0


@numba.njit(cache=False)
def _springs_blocks(x, v, eq, ep8, a2, a3, nb, out, energy):  # pragma: no cover - compiled
    e = 0.0
    for b in range(nb):
        if energy:
            e += blocks.spring_block_energy(x, v, eq, ep8, a2, a3, b, out)
        else:
            blocks.spring_block(x, v, eq, ep8, a2, a3, b, out)
    return e


@numba.njit(cache=False)
def _tets_blocks(x, tq, tp8, kappa, floor, nb, out, barrier, masks):  # pragma: no cover - compiled
    e = 0.0
    for b in range(nb):
        if barrier:
            ev, m = blocks.volume_block_full(x, tq, tp8, kappa, floor, b, out)
        else:
            ev, m = blocks.volume_block_quadratic_full(x, tq, tp8, kappa, floor, b, out)
        e += ev
        masks[b] = m
    return e


@numba.njit(cache=False)
def _tets_forces_only(x, tq, tp8, kappa, floor, nb, out, barrier):  # pragma: no cover - compiled
    for b in range(nb):
        if barrier:
            blocks.volume_block(x, tq, tp8, kappa, floor, b, out)
        else:
            blocks.volume_block_quadratic(x, tq, tp8, kappa, floor, b, out)


def _rows(points: np.ndarray) -> np.ndarray:
    out = step.aligned_zeros((points.shape[0], 4))
    out[:, :3] = points
    return out


def _rel(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a - b).max()) / float(np.abs(b).max())


def _spring_case(rng: np.random.Generator, edges: np.ndarray, n: int):
    rest = 0.01 * (1.0 + rng.random(len(edges)))
    kl0 = 50.0 * (1.0 + rng.random(len(edges))) * rest
    c = 1e-3 * rng.random(len(edges))
    x = 0.02 * rng.standard_normal((n, 3))
    v = 0.1 * rng.standard_normal((n, 3))
    eq = (4 * edges).astype(np.uint32).ravel()
    ep = np.stack([rest, 1.0 / rest, kl0, c], axis=1).ravel()
    ep8 = blocks.block_params([1.0 / rest, kl0, c, rest])
    return _rows(x), _rows(v), eq, ep, ep8


@pytest.mark.parametrize("layout", ["random", "star", "repeated"])
def test_spring_blocks_match_the_scalar_loop(layout):
    rng = np.random.default_rng(1)
    n, E = 40, 64
    if layout == "random":
        edges = np.array([rng.choice(n, 2, replace=False) for _ in range(E)])
    elif layout == "star":  # every edge of a block shares node 0: eight updates of one row
        edges = np.stack([np.zeros(E, int), 1 + rng.integers(0, n - 1, E)], axis=1)
    else:  # the same edge eight times in a block, in both directions
        edges = np.repeat(np.array([[3, 7], [7, 3], [1, 2], [2, 9]] * 2), 8, axis=0)
        E = len(edges)
    x, v, eq, ep, ep8 = _spring_case(rng, edges, n)
    for energy in (False, True):
        out_s = step.aligned_zeros((n, 4))
        e_s = step._edge_pass(x.ravel(), v.ravel(), eq, ep, A2, A3, True, energy, 0, E, out_s.ravel())
        out_b = step.aligned_zeros((n, 4))
        e_b = _springs_blocks(x.ravel(), v.ravel(), eq, ep8, A2, A3, E // 8, out_b.ravel(), energy)
        assert _rel(out_b, out_s) < 1e-13
        assert not out_b[:, 3].any()
        assert abs(e_b - e_s) <= 1e-13 * abs(e_s) if energy else e_b == 0.0
    # Newton's third law: the springs' forces sum to zero
    assert np.abs(out_b.sum(axis=0)).max() < 1e-12 * np.abs(out_b).max()


def _tet_case(rng: np.random.Generator, M: int):
    """M tets on their own nodes (4 M nodes), each a perturbed right-handed reference tet."""
    ref = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]) * 0.01
    P = ref[None] + 0.002 * rng.standard_normal((M, 4, 3)) + rng.standard_normal((M, 1, 3))
    tets = np.arange(4 * M).reshape(M, 4)
    vol0 = np.full(M, 0.01**3 / 6.0) * (1.0 + 0.1 * rng.random(M))
    return P.reshape(-1, 3), tets, vol0


@pytest.mark.parametrize("barrier", [True, False])
def test_volume_blocks_match_the_scalar_loop(barrier):
    rng = np.random.default_rng(2)
    M = 32
    X, tets, vol0 = _tet_case(rng, M)
    # tet 3 nearly flat, tet 12 inverted (J below the barrier's floor), tet 21 degenerate (J = 0)
    X[4 * 3 + 3] = X[4 * 3] + 0.5 * (X[4 * 3 + 1] - X[4 * 3]) + 1e-9 * np.array([0.0, 0.0, 1.0])
    X[[4 * 12 + 1, 4 * 12 + 2]] = X[[4 * 12 + 2, 4 * 12 + 1]]
    X[4 * 21 + 3] = X[4 * 21 + 1]
    x = _rows(X)
    tq = (4 * tets).astype(np.uint32).ravel()
    tp = np.stack([1.0 / (6.0 * vol0), vol0], axis=1).ravel()
    tp8 = blocks.block_params([1.0 / (6.0 * vol0), vol0])
    kappa = 2.0e5
    out_s = step.aligned_zeros((4 * M, 4))
    order = np.arange(M)
    e_s, count, first = step._tet_pass(
        x.ravel(), tq, tp, order, kappa, barrier, True, True, 0, M, out_s.ravel()
    )
    out_b = step.aligned_zeros((4 * M, 4))
    masks = np.zeros(M // 8, np.int64)
    e_b = _tets_blocks(x.ravel(), tq, tp8, kappa, _J_FLOOR, M // 8, out_b.ravel(), barrier, masks)
    assert _rel(out_b, out_s) < 1e-12
    assert abs(e_b - e_s) <= 1e-12 * abs(e_s)
    bad = [8 * b + k for b in range(M // 8) for k in range(8) if (masks[b] >> k) & 1]
    assert (len(bad), bad[0]) == (count, first)
    assert 12 in bad and 21 in bad and count == 2
    out_f = step.aligned_zeros((4 * M, 4))
    _tets_forces_only(x.ravel(), tq, tp8, kappa, _J_FLOOR, M // 8, out_f.ravel(), barrier)
    np.testing.assert_array_equal(out_f, out_b)
    # each tet's four forces sum to zero (the volume term is translation invariant)
    per_tet = out_b[:, :3].reshape(M, 4, 3).sum(axis=1)
    assert np.abs(per_tet).max() < 1e-9 * np.abs(out_b).max()


def test_a_non_finite_position_gives_non_finite_forces_as_the_scalar_loop():
    rng = np.random.default_rng(3)
    M = 8
    X, tets, vol0 = _tet_case(rng, M)
    X[4 * 5 + 2, 1] = np.nan
    x = _rows(X)
    tq = (4 * tets).astype(np.uint32).ravel()
    tp = np.stack([1.0 / (6.0 * vol0), vol0], axis=1).ravel()
    tp8 = blocks.block_params([1.0 / (6.0 * vol0), vol0])
    out_s = step.aligned_zeros((4 * M, 4))
    order = np.arange(M)
    _, count, first = step._tet_pass(x.ravel(), tq, tp, order, 2.0e5, True, False, True, 0, M, out_s.ravel())
    out_b = step.aligned_zeros((4 * M, 4))
    masks = np.zeros(1, np.int64)
    _tets_blocks(x.ravel(), tq, tp8, 2.0e5, _J_FLOOR, 1, out_b.ravel(), True, masks)
    np.testing.assert_array_equal(np.isnan(out_b), np.isnan(out_s))
    assert np.isnan(out_b[4 * 5 : 4 * 6, :3]).any()
    assert (count, first) == (1, 5) and masks[0] == 1 << 5
    finite = ~np.isnan(out_s)
    assert _rel(out_b[finite], out_s[finite]) < 1e-13


def test_block_params_lay_out_eight_of_each_column_a_block():
    a = np.arange(20.0)
    b = -np.arange(20.0)
    p = blocks.block_params([a, b]).reshape(-1, 2, 8)
    assert p.shape == (2, 2, 8)  # 20 elements: two whole blocks, four left for the scalar loop
    np.testing.assert_array_equal(p[1, 0], a[8:16])
    np.testing.assert_array_equal(p[1, 1], b[8:16])
    assert blocks.block_params([np.arange(5.0)]).size == 0


@pytest.mark.parametrize("value,expected", [("1", True), ("on", True), ("0", False), ("False", False)])
def test_the_blocks_switch_reads_the_environment(monkeypatch, value, expected):
    monkeypatch.setenv("SOFTGRASP_BLOCKS", value)
    assert step._blocks_default() is expected


def test_a_bad_blocks_switch_is_refused(monkeypatch):
    monkeypatch.setenv("SOFTGRASP_BLOCKS", "maybe")
    with pytest.raises(ValueError, match="SOFTGRASP_BLOCKS='maybe'"):
        step._blocks_default()


def _node_case(rng: np.random.Generator, n: int, parts: int):
    rows = {name: step.aligned_zeros((n, 4)) for name in ("x", "v", "ref", "grav", "fplane", "ffinger")}
    for name, scale in (("x", 0.05), ("v", 0.1), ("grav", 1e-3), ("fplane", 1e-2), ("ffinger", 1e-2)):
        rows[name][:, :3] = scale * rng.standard_normal((n, 3))
    rows["ref"][:, :3] = rows["x"][:, :3] + 1e-4 * rng.standard_normal((n, 3))
    fint = step.aligned_zeros((parts, n, 4))
    fint[:2, :, :3] = 0.05 * rng.standard_normal((2, n, 3))
    return rows, fint


def _node_pass(rows, fint, mass, dt, part=0, parts=1):
    n = mass.shape[0]
    planes = (
        np.zeros((0, 3)),
        np.zeros((0, 3)),
        np.zeros((0, 3)),
        np.zeros(0),
        *(np.zeros((0, n)) for _ in range(4)),
    )
    sums = np.zeros(6)
    step._node_part(
        part, parts, dt, rows["x"], rows["v"], mass, rows["grav"], fint, rows["fplane"], rows["ffinger"],
        rows["ref"], planes, np.zeros((0, 3)), np.zeros((0, n), np.bool_), np.zeros((0, n, 3)), sums,
    )  # fmt: skip
    return sums


@pytest.mark.parametrize("parts", [1, 2])
@pytest.mark.parametrize("bad_node", [None, 20, 21, 36])
def test_the_node_rows_step_as_the_scalar_loop_to_the_bit(bad_node, parts):
    """The node pass two rows at a time (:data:`softgrasp.sim.fused.blocks.node_pair_step` /
    ``node_pair_step_two``, one or two force parts; the odd node last through ``node_step``) and on
    its scalar loop (taken for three parts, the extra ones zero) give the same bits; a non-finite
    value is seen in either node of a pair and in the last one."""
    nonfinite = bad_node is not None
    rng = np.random.default_rng(4)
    n = 37
    mass = 1e-3 * (1.0 + rng.random(n))
    rows, fint = _node_case(rng, n, 2)
    if parts == 1:
        fint = fint[:1].copy()
    if nonfinite:
        fint[parts - 1, bad_node, 1] = np.inf
    rows3 = {k: v.copy() for k, v in rows.items()}
    r0 = {k: v.copy() for k, v in rows.items()}
    fint3 = step.aligned_zeros((3, n, 4))
    fint3[:parts] = fint
    sums = _node_pass(rows, fint, mass, 1e-5)
    sums3 = _node_pass(rows3, fint3, mass, 1e-5)
    for name in rows:
        np.testing.assert_array_equal(rows[name], rows3[name])
    np.testing.assert_array_equal(sums, sums3)
    assert sums[0] == (1.0 if nonfinite else 0.0)
    assert not rows["fplane"].any() and not rows["ffinger"].any()  # read, then cleared
    assert not rows["x"][:, 3].any() and not rows["v"][:, 3].any()
    # the step itself: v += dt F / m, x += dt v (one part's check, by hand)
    if not nonfinite:
        F = ((fint.sum(axis=0) + r0["grav"]) + r0["fplane"]) + r0["ffinger"]
        v_new = r0["v"] + 1e-5 * (F / mass[:, None])
        np.testing.assert_allclose(rows["v"], v_new, rtol=1e-15, atol=0)
        np.testing.assert_allclose(rows["x"], r0["x"] + 1e-5 * v_new, rtol=1e-15, atol=0)


def test_node_parts_starting_at_an_odd_node_step_as_one_part():
    """Two node parts of 39 nodes (the second starting at node 19, its pairs (19, 20), ...) give the
    rows of one part over all of them to the bit."""
    rng = np.random.default_rng(5)
    n = 39
    mass = 1e-3 * (1.0 + rng.random(n))
    rows, fint = _node_case(rng, n, 2)
    split = {k: v.copy() for k, v in rows.items()}
    _node_pass(rows, fint, mass, 1e-5)
    for part in (0, 1):
        _node_pass(split, fint, mass, 1e-5, part, 2)
    for name in rows:
        np.testing.assert_array_equal(rows[name], split[name])


def test_the_check_energy_logarithm_matches_a_long_double_reference():
    """The barrier energy kappa V0 (J - 1 - log J) of the check steps (:data:`volume_block_full`,
    whose log is computed in vector instructions) against long-double arithmetic, for J from the
    floor up to 1e3: right-angled tets with power-of-two legs make J exact, so the comparison sees
    the logarithm's error alone (a few ulp of log J, which near J = 1 is also what bounds psi)."""
    targets = [
        1e-13,
        1e-9,
        1e-3,
        0.3,
        0.7071,
        0.75,
        1.0 - 2.0**-20,
        1.0,
        1.0 + 2.0**-10,
        1.4142,
        1.5,
        3.0,
        1e3,
    ]
    M = 8 * len(targets)
    leg = 2.0**-7
    X = np.zeros((4 * M, 3))
    for b, J in enumerate(targets):
        for k in range(8):
            t = 8 * b + k
            X[4 * t + 1] = [leg, 0.0, 0.0]
            X[4 * t + 2] = [0.0, leg, 0.0]
            X[4 * t + 3] = [0.0, 0.0, J * leg]  # det = J 2^-21 exactly
    tets = np.arange(4 * M).reshape(M, 4)
    vol0 = np.full(M, 2.0**-21 / 6.0)
    tq = (4 * tets).astype(np.uint32).ravel()
    tp8 = blocks.block_params([1.0 / (6.0 * vol0), vol0])
    assert (tp8.reshape(-1, 2, 8)[:, 0] == 2.0**21).all()  # 1 / (6 V0) exact: J exact
    kappa = 2.0e5
    out = step.aligned_zeros((4 * M, 4))
    masks = np.zeros(M // 8, np.int64)
    energies = [
        _tets_blocks(
            _rows(X).ravel(),
            tq[32 * b : 32 * (b + 1)],
            tp8[16 * b : 16 * (b + 1)],
            kappa,
            _J_FLOOR,
            1,
            out.ravel(),
            True,
            masks,
        )
        for b in range(len(targets))
    ]
    ld = np.longdouble
    for b, J in enumerate(targets):
        Jc = max(J, _J_FLOOR)
        psi = ld(J) - ld(1) - np.log(ld(Jc))
        expect = ld(8) * ld(kappa) * ld(vol0[0]) * psi
        # a few ulp of log J (near J = 1 that bounds psi's error), and the rounding of psi, of the
        # products and of the sum of the eight lanes
        eps = np.finfo(float).eps
        tol = 8 * kappa * vol0[0] * (4 * eps * abs(np.log(Jc)) + 8 * eps * float(psi))
        assert abs(ld(energies[b]) - expect) <= tol, (J, energies[b], float(expect))
