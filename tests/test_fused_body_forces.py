"""The fused stepper's body forces (:mod:`softgrasp.sim.fused.body` on the layout of its
:func:`~softgrasp.sim.fused.body.pack_body`) against the NumPy reference (the oracle
:mod:`oracles.forces`: ``body_internal_forces`` / ``body_internal_energy``) on perturbed
states: forces, energy, inverted tets; with and without the volume term, the barrier and the
quadratic volume law, damped and undamped, split in one to five parts."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from oracles import forces as ref
from softgrasp.model.material import Material, Polynomial
from softgrasp.model.mesh import TetMesh, box, signed_volumes
from softgrasp.model.objects import make_object
from softgrasp.physics.body import build_body

pytest.importorskip("numba")
from softgrasp.sim.fused import body as fused_body  # noqa: E402 - needs numba

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


def _fused(body, x, v, want_energy: bool, check: bool, parts: int = 2, parallel: bool = False):
    """Summed forces [N] (N, 3), energy [J], inverted count and first inverted tet."""
    fint = np.zeros((parts, body.n_nodes, 3))
    info = np.zeros((parts, 3))
    packed = fused_body.pack_body(body)
    x, v = np.ascontiguousarray(x), np.ascontiguousarray(v)
    e, count, first = fused_body.body_forces(parallel, x, v, packed, want_energy, check, fint, info)
    return fint.sum(axis=0), e, count, first


def _reference(body, x, v):
    return ref.body_internal_forces(body, x, v), ref.body_internal_energy(body, x)


@pytest.mark.parametrize("name", ["sphere", "cube"])
@pytest.mark.parametrize("kappa", ["body", "zero", "quadratic"])
@pytest.mark.parametrize("parts", [1, 2, 3])
def test_forces_and_energy_match_the_reference(request, name, kappa, parts):
    body = request.getfixturevalue(name)
    if kappa == "zero":
        body = dataclasses.replace(body, kappa=0.0)
    elif kappa == "quadratic":  # kappa < 0: the quadratic volume law, no barrier
        body = dataclasses.replace(body, kappa=-abs(body.kappa))
    x, v = _state(body, seed=parts)
    f_ref, e_ref = _reference(body, x, v)
    for want_energy, check in ((False, False), (True, True), (True, False), (False, True)):
        for parallel in (False, True):
            f, e, count, first = _fused(body, x, v, want_energy, check, parts, parallel)
            assert _rel(f, f_ref) < TOL
            assert (abs(e - e_ref) <= TOL * abs(e_ref)) if want_energy else e == 0.0
            assert (count, first) == (0, -1)


def test_threads_give_the_same_sums_to_the_bit(sphere):
    """The parts are summed in the same order on one thread or on Numba's threads."""
    x, v = _state(sphere, seed=5)
    one = _fused(sphere, x, v, True, True, 2, parallel=False)
    two = _fused(sphere, x, v, True, True, 2, parallel=True)
    assert np.array_equal(one[0], two[0]) and one[1:] == two[1:]


def test_the_parts_clear_whatever_their_buffers_held(sphere):
    """Each part clears its whole buffer: NaN, -0.0 and stale forces left in it from before change
    nothing."""
    x, v = _state(sphere, seed=6)
    f_ref, _ = _reference(sphere, x, v)
    packed = fused_body.pack_body(sphere)
    fint = np.random.default_rng(2).standard_normal((2, sphere.n_nodes, 3))
    fint[0, ::3] = np.nan
    fint[1, ::5] = -0.0
    info = np.zeros((2, 3))
    fused_body.body_forces(False, x, v, packed, False, False, fint, info)
    assert _rel(fint.sum(axis=0), f_ref) < TOL


def test_pack_body_refuses_a_law_that_is_not_a_polynomial(sphere):
    from softgrasp.model.material import Tabulated

    body = build_body(
        box(0.02, 1), Material(1e5, 0.45, 50.0, law=Tabulated([0.05, 0.1, 0.2], [5e3, 1e4, 2.1e4]))
    )
    with pytest.raises(ValueError, match="not a polynomial"):
        fused_body.pack_body(body)


@pytest.mark.parametrize("law", ["barrier", "quadratic"])
def test_undamped_forces_match_the_reference(sphere, law):
    body = dataclasses.replace(sphere, damping_time=0.0)
    if law == "quadratic":
        body = dataclasses.replace(body, kappa=-abs(body.kappa))
    x, v = _state(body, seed=3)
    f_ref, e_ref = ref.body_internal_forces(body, x), ref.body_internal_energy(body, x)
    for check in (False, True):
        f, e, count, first = _fused(body, x, v, check, check)
        assert _rel(f, f_ref) < TOL and (count, first) == (0, -1)
        assert abs(e - e_ref) <= TOL * abs(e_ref) if check else e == 0.0


@pytest.mark.parametrize("kappa", ["body", "zero", "quadratic"])
def test_inverted_tets_are_counted_when_checked(sphere, kappa):
    body = sphere
    if kappa != "body":
        body = dataclasses.replace(sphere, kappa=0.0 if kappa == "zero" else -abs(sphere.kappa))
    x, v = _state(body, seed=4, scale=0.05)
    tets = np.asarray(body.mesh.tets)
    M = len(tets)
    for t in (M - 1, 11, 12, M // 2 + 1):  # swap two nodes: those tets invert (in both parts)
        a, b = tets[t, 0], tets[t, 1]
        x[[a, b]] = x[[b, a]]
    bad = np.flatnonzero(~(signed_volumes(x, tets) > 0))
    assert bad.size >= 3 and bad[-1] >= M // 2 and bad[0] < M // 2
    f_ref, e_ref = _reference(body, x, v)
    for parts in (1, 2, 3):
        f, e, count, first = _fused(body, x, v, True, True, parts)
        assert (count, first) == (bad.size, bad[0])
        assert _rel(f, f_ref) < TOL
        assert abs(e - e_ref) <= TOL * abs(e_ref)
        assert _fused(body, x, v, False, True, parts)[2:] == (bad.size, bad[0])
        assert _fused(body, x, v, False, False, parts)[2:] == (0, -1)


def test_nearly_flat_tets_are_found_inverted_as_the_reference_finds_them():
    """Without the volume term the fused pass counts inverted tets with the unfused triple product
    of :func:`softgrasp.physics.volume._inverted` (the kernel of ``count_inverted``): on 20 000
    nearly flat tets, whose sign is decided by the last bits, the same tets."""
    from softgrasp.physics import volume as elastic

    rng = np.random.default_rng(0)
    M = 20_000
    P = rng.standard_normal((M, 4, 3))
    n = rng.standard_normal((M, 1, 3))
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    P = P - (P * n).sum(2, keepdims=True) * n + 1e-16 * rng.standard_normal((M, 4, 1)) * n
    x = (P * 1e-2 + rng.standard_normal((M, 1, 3))).reshape(-1, 3)
    tets = np.arange(4 * M, dtype=np.int64).reshape(M, 4)
    ones = np.ones(M)
    packed = (np.zeros((0, 2), np.int64), *(np.zeros(0) for _ in range(4)), tets, ones, ones, 0.0, 0.0,
              False, 0.0, True, len(x))  # fmt: skip
    old = np.array([elastic._inverted(x, tets, t, t + 1)[0] > 0 for t in range(M)])
    assert 0 < old.sum() < M
    for parts in (1, 3):
        fint, info = np.zeros((parts, len(x), 3)), np.zeros((parts, 3))
        count, first = fused_body.body_forces(False, x, x, packed, False, True, fint, info)[1:]
        assert (count, first) == (old.sum(), np.flatnonzero(old)[0])
        for p in range(parts):  # each part's own count: its share of the tets
            lo, hi = p * M // parts, (p + 1) * M // parts
            assert info[p, 1] == old[lo:hi].sum()


@pytest.mark.filterwarnings("ignore:the springs of mesh:UserWarning")  # one tet is not isotropic
@pytest.mark.parametrize("shape", ["tet", "box1", "box2"])
@pytest.mark.parametrize("parts", [1, 2, 5, 8])
def test_small_bodies_and_more_parts_than_elements(shape, parts):
    """A single tet (six springs), a one-cell box (24 tets) and a two-cell one, split in up to eight
    parts (more parts than the tet's elements): every element counted once."""
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
        f, e, count, first = _fused(body, x, v, want_energy, check, parts)
        assert _rel(f, f_ref) < TOL
        assert (abs(e - e_ref) <= TOL * abs(e_ref)) if want_energy else e == 0.0


def test_mismatched_arrays_are_refused(sphere):
    packed = fused_body.pack_body(sphere)
    x, v = _state(sphere)
    info = np.zeros((2, 3))
    fint = np.zeros((2, sphere.n_nodes, 3))
    with pytest.raises(ValueError, match="fint"):  # a 4-wide force buffer
        fused_body.body_forces(False, x, v, packed, False, False, np.zeros((2, sphere.n_nodes, 4)), info)
    with pytest.raises(ValueError, match="x and v"):  # (N, 4) positions
        fused_body.body_forces(False, np.zeros((len(x), 4)), v, packed, False, False, fint, info)
    with pytest.raises(ValueError, match="x and v"):  # a row short
        fused_body.body_forces(False, x, v[:-1].copy(), packed, False, False, fint, info)
