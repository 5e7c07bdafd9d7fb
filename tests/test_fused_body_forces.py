"""The fused stepper's body forces (:mod:`softgrasp.sim.fused.step` on the layout of its
:func:`~softgrasp.sim.fused.step.pack_body`) against the NumPy oracle (:mod:`oracles.forces`, ``body_internal_forces`` /
``body_internal_energy``) on perturbed
states: forces, energy, inverted tets; with and without the volume term, the barrier and the
quadratic volume law, damped and undamped, split in one to three parts."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from oracles import forces as ref

from softgrasp.physics.body import build_body
from softgrasp.model.material import Material, Polynomial
from softgrasp.model.mesh import TetMesh, box, signed_volumes
from softgrasp.model.objects import make_object

pytest.importorskip("numba")
from softgrasp.sim.fused import blocks, step  # noqa: E402 - needs numba

TOL = 1e-10


def _rel(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a - b).max()) / float(np.abs(b).max())


@pytest.fixture(scope="module")
def sphere():
    mesh, mat, mass = make_object("sphere", 0.014)
    return build_body(mesh, mat, mass=mass)


@pytest.fixture(scope="module")
def cube():
    """A box of the cubic law (a2, a3 != 0)."""
    return build_body(box(0.03, 3), Material(0.0793e6, 0.45, 45.5, law=Polynomial(0.4, 2.0)), mass=0.02)


def _state(body, seed: int = 0, scale: float = 0.15) -> tuple[np.ndarray, np.ndarray]:
    """Positions moved by ``scale`` of the shortest edge at random, random velocities."""
    rng = np.random.default_rng(seed)
    x0 = np.asarray(body.mesh.points, dtype=np.float64)
    h = float(body.rest_length.min())
    return x0 + scale * h * rng.standard_normal(x0.shape), 0.05 * rng.standard_normal(x0.shape)


def _rows(a: np.ndarray) -> np.ndarray:
    """(N, 3) values as the stepper's (N, 4) rows, the fourth column zero."""
    out = step.aligned_zeros((a.shape[0], 4))
    out[:, :3] = a
    return out


def _fused(body, x, v, want_energy: bool, check: bool, parts: int = 2, blocks: bool | None = None):
    """Summed forces [N] (N, 3), energy [J], inverted count and first inverted tet."""
    fint = np.zeros((parts, body.n_nodes, 4))
    info = np.zeros((parts, 3))
    packed = step.pack_body(body, blocks)
    e, count, first = step._body_forces(False, _rows(x), _rows(v), packed, want_energy, check, fint, info)
    assert not fint[:, :, 3].any()
    return fint[:, :, :3].sum(axis=0), e, count, first


def _reference(body, x, v):
    return ref.body_internal_forces(body, x, v), ref.body_internal_energy(body, x)


@pytest.mark.parametrize("name", ["sphere", "cube"])
@pytest.mark.parametrize("kappa", ["body", "zero", "quadratic"])
@pytest.mark.parametrize("parts", [1, 2, 3])
@pytest.mark.parametrize("blocks", [True, False])
def test_forces_and_energy_match_the_reference(request, name, kappa, parts, blocks):
    body = request.getfixturevalue(name)
    if kappa == "zero":
        body = dataclasses.replace(body, kappa=0.0)
    elif kappa == "quadratic":  # kappa < 0: the quadratic volume law, no barrier
        body = dataclasses.replace(body, kappa=-abs(body.kappa))
    x, v = _state(body, seed=parts)
    f_ref, e_ref = _reference(body, x, v)
    for want_energy, check in ((False, False), (True, True), (True, False), (False, True)):
        f, e, count, first = _fused(body, x, v, want_energy, check, parts, blocks)
        assert _rel(f, f_ref) < TOL
        assert (abs(e - e_ref) <= TOL * abs(e_ref)) if want_energy else e == 0.0
        assert (count, first) == (0, -1)


@pytest.mark.parametrize("lead", [0.25, 0.43, 0.8])
@pytest.mark.parametrize("blocks", [True, False])
def test_two_parts_split_the_elements_at_the_lead_share(sphere, lead, blocks):
    """pack_body's ``lead``: the first of two parts takes that share of the elements (its blocks
    with the block kernels), the second the rest, and together they are the reference's forces.
    The split is read off the inverted counts of a mirrored body, every tet of which is inverted."""
    x, v = _state(sphere, seed=5)
    f_ref, _ = _reference(sphere, x, v)
    packed = step.pack_body(sphere, blocks, lead)
    fint, info = np.zeros((2, sphere.n_nodes, 4)), np.zeros((2, 3))
    step._body_forces(False, _rows(x), _rows(v), packed, False, False, fint, info)
    assert _rel(fint[:, :, :3].sum(axis=0), f_ref) < TOL
    M = len(sphere.mesh.tets)
    first = 8 * int(M // 8 * lead) if blocks else int(M * lead)
    step._body_forces(False, _rows(-x), _rows(v), packed, False, True, fint, info)  # (J floored)
    assert (info[0, 1], info[1, 1]) == (first, M - first)


def test_the_parts_clear_whatever_their_buffers_held(sphere):
    """Each part clears its whole buffer (writing only where it is not zero yet): NaN, -0.0 and
    stale forces left in it from before change nothing."""
    x, v = _state(sphere, seed=6)
    f_ref, _ = _reference(sphere, x, v)
    packed = step.pack_body(sphere)
    fint = np.random.default_rng(2).standard_normal((2, sphere.n_nodes, 4))
    fint[0, ::3] = np.nan
    fint[1, ::5] = -0.0
    info = np.zeros((2, 3))
    step._body_forces(False, _rows(x), _rows(v), packed, False, False, fint, info)
    assert _rel(fint[:, :, :3].sum(axis=0), f_ref) < TOL and not fint[:, :, 3].any()


def test_pack_body_refuses_a_share_outside_the_unit_interval(sphere):
    for lead in (0.0, 1.0, -0.2, float("nan")):
        with pytest.raises(ValueError, match="share"):
            step.pack_body(sphere, lead=lead)


def test_leader_share_gives_way_to_the_fingertips():
    assert step.leader_share(0, 20_000) == 0.5
    one, three = step.leader_share(1, 22_696), step.leader_share(3, 22_696)
    assert 0.25 <= three < one < 0.5 and abs(one - 0.425) < 0.01  # (the measured best at 2 196 nodes)
    assert step.leader_share(1, 5_000) < one < step.leader_share(1, 85_000) < 0.5  # the body's share grows
    assert step.leader_share(10, 5_000) == 0.25


@pytest.mark.parametrize("law", ["barrier", "quadratic"])
@pytest.mark.parametrize("blocks", [True, False])
def test_undamped_forces_match_the_reference(sphere, blocks, law):
    body = dataclasses.replace(sphere, damping_time=0.0)
    if law == "quadratic":
        body = dataclasses.replace(body, kappa=-abs(body.kappa))
    x, v = _state(body, seed=3)
    f_ref, e_ref = ref.body_internal_forces(body, x), ref.body_internal_energy(body, x)
    for check in (False, True):
        f, e, count, first = _fused(body, x, v, check, check, blocks=blocks)
        assert _rel(f, f_ref) < TOL and (count, first) == (0, -1)
        assert abs(e - e_ref) <= TOL * abs(e_ref) if check else e == 0.0


@pytest.mark.parametrize("kappa", ["body", "zero", "quadratic"])
@pytest.mark.parametrize("blocks", [True, False])
def test_inverted_tets_are_counted_when_checked(sphere, kappa, blocks):
    body = sphere
    if kappa != "body":
        body = dataclasses.replace(sphere, kappa=0.0 if kappa == "zero" else -abs(sphere.kappa))
    x, v = _state(body, seed=4, scale=0.05)
    tets = np.asarray(body.mesh.tets)
    order = step.pack_body(body, blocks)[13]  # the mesh's tets in the kernels' order
    last = order[-1]
    # with the block kernels, two tets met in the reverse of the mesh's order (the lower last)
    k = int(np.flatnonzero(order[:-1] > order[1:])[0]) if blocks else 11
    for t in (last, order[k], order[k + 1], len(tets) // 2):  # swap two nodes: those tets invert
        a, b = tets[t, 0], tets[t, 1]
        x[[a, b]] = x[[b, a]]
    bad = np.flatnonzero(~(signed_volumes(x, tets) > 0))
    assert bad.size >= 3
    assert len(tets) % 8 and last in bad  # one among the tets left over after the blocks of eight
    # the kernels meet the inverted tets in their own order and report the lowest mesh index
    met = [t for t in order if t in set(bad)]
    assert met[0] != bad[0] or not blocks
    f_ref, e_ref = _reference(body, x, v)
    for parts in (1, 2):
        f, e, count, first = _fused(body, x, v, True, True, parts, blocks)
        assert (count, first) == (bad.size, bad[0])
        assert _rel(f, f_ref) < TOL
        assert abs(e - e_ref) <= TOL * abs(e_ref)
        assert _fused(body, x, v, False, True, parts, blocks)[2:] == (bad.size, bad[0])
        assert _fused(body, x, v, False, False, parts, blocks)[2:] == (0, -1)


def test_nearly_flat_tets_are_found_inverted_as_the_reference_finds_them():
    """Without the volume term the fused pass counts inverted tets with the same unfused triple
    product as :func:`softgrasp.physics.volume._inverted` (the kernel of ``count_inverted``):
    on 20 000 nearly flat tets, whose sign is decided by the last bits, the same tets."""
    import numba

    from softgrasp.physics import volume as elastic

    rng = np.random.default_rng(0)
    M = 20_000
    P = rng.standard_normal((M, 4, 3))
    n = rng.standard_normal((M, 1, 3))
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    P = P - (P * n).sum(2, keepdims=True) * n + 1e-16 * rng.standard_normal((M, 4, 1)) * n
    x = (P * 1e-2 + rng.standard_normal((M, 1, 3))).reshape(-1, 3)
    tets = np.arange(4 * M, dtype=np.int64).reshape(M, 4)
    tq = (3 * tets).astype(np.uint32).ravel()

    @numba.njit
    def each(x, xf, tets, tq, old, new):  # pragma: no cover - compiled
        out = np.zeros(xf.size)
        tp = np.ones(2 * tets.shape[0])
        order = np.arange(tets.shape[0])
        for t in range(tets.shape[0]):
            old[t] = elastic._inverted(x, tets, t, t + 1)[0] > 0
            new[t] = step._tet_pass(xf, tq, tp, order, 0.0, True, False, True, t, t + 1, out)[1] > 0

    old = np.zeros(M, dtype=np.bool_)
    new = np.zeros(M, dtype=np.bool_)
    each(x, x.ravel(), tets, tq, old, new)
    assert 0 < old.sum() < M
    np.testing.assert_array_equal(new, old)


@pytest.mark.filterwarnings("ignore:the springs of mesh:UserWarning")  # one tet is not isotropic
@pytest.mark.parametrize("shape", ["tet", "box1", "box2"])
@pytest.mark.parametrize("parts", [1, 2, 5])
@pytest.mark.parametrize("blocks", [True, False])
def test_small_bodies_and_more_parts_than_blocks(shape, parts, blocks):
    """A single tet (six springs: no block at all), a one-cell box (24 tets, three blocks) and a
    two-cell one, split in up to five parts: every element counted once."""
    if shape == "tet":
        mesh = TetMesh(
            0.01 * np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]), np.array([[0, 1, 2, 3]])
        )
    else:
        mesh = box(0.02, int(shape[-1]))
    body = build_body(mesh, Material(0.0793e6, 0.45, 45.5), mass=0.01)
    x, v = _state(body, seed=6)
    f_ref, e_ref = _reference(body, x, v)
    for want_energy, check in ((False, False), (True, True)):
        f, e, count, first = _fused(body, x, v, want_energy, check, parts, blocks)
        assert _rel(f, f_ref) < TOL
        assert (abs(e - e_ref) <= TOL * abs(e_ref)) if want_energy else e == 0.0


def test_mismatched_arrays_are_refused(sphere):
    packed = step.pack_body(sphere)
    x, v = _state(sphere)
    x4, v4 = _rows(x), _rows(v)
    info = np.zeros((2, 3))
    fint = np.zeros((2, sphere.n_nodes, 4))
    with pytest.raises(ValueError, match="fint"):  # a 3-wide force buffer
        step._body_forces(False, x4, v4, packed, False, False, np.zeros((2, sphere.n_nodes, 3)), info)
    with pytest.raises(ValueError, match="x and v"):  # (N, 3) positions: not the stepper's rows
        step._body_forces(False, x, v, packed, False, False, fint, info)
    with pytest.raises(ValueError, match="x and v"):  # a row short
        step._body_forces(False, x4, v4[:-1].copy(), packed, False, False, fint, info)


@pytest.mark.parametrize("kind", ["edges", "tets"])
def test_block_order_keeps_a_block_free_of_repeated_nodes(sphere, kind):
    """The block kernels' element order (:func:`step._block_order`): a permutation whose blocks of
    eight share no node (the mesh's own order repeats nodes in most blocks), elements moved only a
    short way; and the packed body is that order (forces to round-off: the tests above)."""
    elems = np.asarray(sphere.edges if kind == "edges" else sphere.mesh.tets, dtype=np.int64)
    n = len(elems)
    order = step._block_order(elems, step._ORDER_WINDOW)
    assert np.array_equal(np.sort(order), np.arange(n))

    def repeats(o):  # nodes met twice, block by block
        blocks = elems[o[: 8 * (n // 8)]].reshape(n // 8, -1)
        return np.array([b.size - np.unique(b).size for b in blocks])

    assert repeats(np.arange(n)).sum() > n // 8  # the mesh's order: more than one a block
    # repeats only where the elements run out: among the last 16 blocks
    assert np.flatnonzero(repeats(order)).min(initial=n) >= n // 8 - 16
    assert np.abs(order - np.arange(n)).max() <= step._ORDER_WINDOW + 8
    if kind == "tets":  # (each tet's vertices in the order that brings its spring to vertices 0, 1)
        packed = step.pack_body(sphere, True)
        assert np.array_equal(packed[13], order)
        assert np.array_equal(np.sort(packed[2].reshape(-1, 4), axis=1), 4 * np.sort(elems[order], axis=1))
    else:  # without the volume term no tet carries a spring: all of them in their block order
        packed = step.pack_body(dataclasses.replace(sphere, kappa=0.0), True)
        assert not packed[15] and np.array_equal(packed[0].reshape(-1, 2), 4 * elems[order])
    assert np.array_equal(step.pack_body(sphere, False)[13], np.arange(len(sphere.mesh.tets)))


@pytest.mark.parametrize("name", ["sphere", "cube"])
def test_tets_carry_each_spring_at_most_once_the_rest_go_alone(request, name):
    """pack_body with the volume term and the block kernels: the tets of whole blocks carry a
    spring each between their vertices 0 and 1 (an even reordering of the mesh's vertices, so the
    signed volume keeps its sign); every spring is carried by one tet or packed alone, never both,
    with its own rest length, stiffness and damping. (Forces and energy to round-off of the
    reference: the tests above.)"""
    body = request.getfixturevalue(name)
    packed = step.pack_body(body, True)
    assert packed[15]
    tets = packed[2].reshape(-1, 4) // 4
    M = len(tets)
    x = np.asarray(body.mesh.points)
    mesh_tets = np.asarray(body.mesh.tets)[packed[13]]
    np.testing.assert_allclose(signed_volumes(x, tets), signed_volumes(x, mesh_tets), rtol=1e-12)
    cols = packed[11].reshape(M // 8, -1, 8)  # a block: 1 / (6 V0), V0, then the spring's columns
    assert cols.shape[1] == blocks.TET_SPRING_COLUMNS
    index = {tuple(sorted(e)): k for k, e in enumerate(np.asarray(body.edges).tolist())}
    kl0 = np.asarray(body.stiffness) * np.asarray(body.rest_length)
    carried = []
    for t in range(8 * (M // 8)):
        inv_l0, k, c, l0 = cols[t // 8, 2:, t % 8]
        if k == 0.0:
            assert (inv_l0, c, l0) == (1.0, 0.0, 1.0)  # none: no force, no energy
            continue
        e = index[tuple(sorted((tets[t, 0], tets[t, 1])))]  # a spring of the body between them
        assert (l0, inv_l0, k) == (body.rest_length[e], 1.0 / body.rest_length[e], kl0[e])
        assert c == pytest.approx(body.damping[e], rel=1e-15)
        carried.append(e)
    alone = [index[tuple(sorted(e))] for e in (packed[0].reshape(-1, 2) // 4).tolist()]
    assert sorted(carried + alone) == list(range(len(body.edges)))  # each spring exactly once
    assert len(carried) > 0.95 * 8 * (M // 8)  # nearly every tet carries one
