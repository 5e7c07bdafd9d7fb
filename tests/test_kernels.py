"""The compiled (Numba) kernels agree with the NumPy oracles of ``tests/oracles`` to 1e-8.

Agreement is measured as max |fast - reference| / max |reference| over forces, energies and
Jacobians, for the linear law, every non-linear law of :mod:`softgrasp.model.material` and a user-defined
law, with the volume barrier on and off, on randomly perturbed sphere and box meshes; and over
the fingertip contact's pairs, dynamic forces and friction-state updates (both contact rules, both
damping forms, with and without friction, sticking and slipping pairs).
"""

from __future__ import annotations

import numba
import numpy as np
import pytest
import scipy.sparse as sp

from oracles import forces as ref
from oracles.contact import OracleFingertipContact, oracle_detect, oracle_scene, pair_geometry
from softgrasp import backend
from softgrasp.model.material import Linear, Material, Polynomial, Tabulated
from softgrasp.model.mesh import box, signed_volumes
from softgrasp.model.objects import make_object
from softgrasp.physics import forces_compiled as elastic
from softgrasp.physics import springs, volume
from softgrasp.physics.body import build_body
from softgrasp.physics.fingertip.contact import FingertipContact
from softgrasp.physics.fingertip.geometry import FacetIndex, detect
from softgrasp.physics.fingertip.params import ContactParams, Fingertip
from softgrasp.physics.planes import Plane, PlaneContact
from softgrasp.sim import Scene, simulate, stable_time_step

TOL = 1e-8


class SoftTanh:
    """A law softgrasp does not define: s = tanh(eps) (a general Python object, no coefficients)."""

    def stress(self, strain):
        return np.tanh(strain)

    def tangent(self, strain):
        return 1.0 / np.cosh(strain) ** 2

    def energy(self, strain):
        return np.log(np.cosh(strain))

    def describe(self):
        return {"kind": "tanh"}


class ShiftedPolynomial(Polynomial):
    """A Polynomial subclass with its own stress: must not be taken for a plain polynomial."""

    def stress(self, strain):
        return super().stress(strain) + 0.1 * np.asarray(strain) ** 2

    def tangent(self, strain):
        return super().tangent(strain) + 0.2 * np.asarray(strain)

    def energy(self, strain):
        return super().energy(strain) + 0.1 * np.asarray(strain) ** 3 / 3.0


LAWS = {
    "linear": Linear(),
    "polynomial": Polynomial(a2=-0.4, a3=1.5),
    "softening": Polynomial(a2=0.1, a3=-0.3),
    "tabulated": Tabulated(np.array([0.05, 0.1, 0.2, 0.3]), np.array([5e3, 1.1e4, 2.6e4, 5e4])),
    "tanh": SoftTanh(),
    "subclass": ShiftedPolynomial(a3=0.5),
}


def _rel(fast, reference) -> float:
    """max |fast - reference| / max |reference| (dense or sparse, arrays or scalars)."""
    a = fast.toarray() if sp.issparse(fast) else np.asarray(fast, dtype=np.float64)
    b = reference.toarray() if sp.issparse(reference) else np.asarray(reference, dtype=np.float64)
    assert a.shape == b.shape
    scale = np.abs(b).max()
    assert scale > 0
    return float(np.abs(a - b).max() / scale)


def _perturbed(mesh, seed: int, amplitude: float):
    rng = np.random.default_rng(seed)
    x = np.asarray(mesh.points) + amplitude * rng.standard_normal(mesh.points.shape)
    assert (signed_volumes(x, mesh.tets) > 0.2 * mesh.volumes).all()
    v = 0.05 * rng.standard_normal(mesh.points.shape)
    return x, v


@pytest.fixture(scope="module", params=["sphere", "box"])
def config(request):
    """A mesh and a randomly perturbed configuration (positions [m], velocities [m/s])."""
    if request.param == "sphere":
        mesh = make_object("sphere", 0.014)[0]
        x, v = _perturbed(mesh, 11, 4e-4)
    else:
        mesh = box(0.04, 3)
        x, v = _perturbed(mesh, 12, 6e-4)
    return mesh, x, v


# ------------------------------------------------------------------------------- the kernels
@pytest.mark.parametrize("law", LAWS.values(), ids=LAWS.keys())
def test_spring_kernels_agree(config, law):
    mesh, x, v = config
    body = build_body(mesh, Material(1e5, 0.45, 50.0, law))
    args = (x, mesh.edges, body.rest_length, body.stiffness, law)
    f1, e1 = springs.spring_forces(*args)
    f0, e0 = ref.spring_forces(*args)
    assert _rel(f1, f0) < TOL
    assert _rel(e1, e0) < TOL
    for psd in (False, True):
        b1 = springs.spring_jacobian_blocks(*args, psd=psd)
        assert _rel(b1, ref.spring_jacobian_blocks(*args, psd=psd)) < TOL
    d1 = springs.edge_damping_forces(x, v, mesh.edges, body.damping)
    assert _rel(d1, ref.edge_damping_forces(x, v, mesh.edges, body.damping)) < TOL


@pytest.mark.parametrize("barrier", [True, False], ids=["barrier", "quadratic"])
@pytest.mark.parametrize("kappa", [2.7e5, -1.4e4])
def test_volume_kernels_agree(config, barrier, kappa):
    mesh, x, _ = config
    args = (x, mesh.tets, mesh.volumes, kappa, barrier)
    f1, e1 = volume.volume_forces(*args)
    f0, e0 = ref.volume_forces(*args)
    assert _rel(f1, f0) < TOL
    assert _rel(e1, e0) < TOL
    assert _rel(volume.volume_jacobian_blocks(*args), ref.volume_jacobian_blocks(*args)) < TOL


def test_volume_kernels_agree_on_an_inverted_tet(config):
    """Past the barrier's floor (J <= 0) both paths use psi at J = 1e-12 the same way."""
    mesh, x, _ = config
    x = x.copy()
    t = mesh.tets[0]
    x[t[3]] = x[t[0]] + (x[t[0]] - x[t[3]])  # reflect node 3 through node 0: the tet inverts
    assert signed_volumes(x, mesh.tets)[0] < 0
    args = (x, mesh.tets, mesh.volumes, 2.7e5, True)
    f1, e1 = volume.volume_forces(*args)
    f0, e0 = ref.volume_forces(*args)
    assert _rel(f1, f0) < TOL
    assert _rel(e1, e0) < TOL
    assert _rel(volume.volume_jacobian_blocks(*args), ref.volume_jacobian_blocks(*args)) < TOL


def test_inverted_tets_counted_as_the_signed_volumes_say(config):
    """The static solver's compiled validity test counts exactly the tets whose NumPy signed
    volume is not positive: none at rest, the reflected ones, and a NaN position's tets."""
    mesh, x, _ = config
    assert elastic.count_inverted(x, mesh.tets) == 0
    x = x.copy()
    for t in mesh.tets[:7:3]:
        x[t[3]] = x[t[0]] + (x[t[0]] - x[t[3]])
    want = int((~(signed_volumes(x, mesh.tets) > 0)).sum())
    assert want >= 3
    assert elastic.count_inverted(x, mesh.tets) == want
    x[mesh.tets[-1, 2]] = np.nan
    assert elastic.count_inverted(x, mesh.tets) == int((~(signed_volumes(x, mesh.tets) > 0)).sum()) > want


# ------------------------------------------------------------------------------- the body
@pytest.mark.parametrize("law", LAWS.values(), ids=LAWS.keys())
@pytest.mark.parametrize("nu", [0.2, 0.45], ids=["quadratic", "barrier"])
def test_body_agrees_with_the_oracle(config, law, nu):
    """Body.internal_forces (with and without dampers), internal_energy and internal_jacobian."""
    mesh, x, v = config
    body = build_body(mesh, Material(1e5, nu, 50.0, law))
    assert body.barrier == (nu > 0.25)
    out = {
        "numba": (
            body.internal_forces(x, v),
            body.internal_forces(x),
            body.internal_energy(x),
            body.internal_jacobian(x),
        ),
        "numpy": (
            ref.body_internal_forces(body, x, v),
            ref.body_internal_forces(body, x),
            ref.body_internal_energy(body, x),
            ref.body_internal_jacobian(body, x),
        ),
    }
    for fast, slow in zip(out["numba"], out["numpy"], strict=True):
        assert _rel(fast, slow) < TOL
    # The compiled Jacobian fills the same CSR structure.
    J1, J0 = out["numba"][3], out["numpy"][3]
    assert np.array_equal(J1.indptr, J0.indptr) and np.array_equal(J1.indices, J0.indices)


def test_body_agrees_with_the_oracle_without_damping_or_volume_term(config):
    """nu = 1/4 (kappa = 0: springs only) and an undamped body take the other branches."""
    mesh, x, v = config
    body = build_body(mesh, Material(1e5, 0.25, 50.0, LAWS["polynomial"]), damping_ratio=0.0)
    fast = (body.internal_forces(x, v), body.internal_energy(x), body.internal_jacobian(x))
    slow = (ref.body_internal_forces(body, x, v), ref.body_internal_energy(body, x), ref.body_internal_jacobian(body, x))
    for a, b in zip(fast, slow, strict=True):
        assert _rel(a, b) < TOL


def test_the_jacobian_assembly_groups_write_no_entry_in_common_and_any_thread_count_gives_the_same_bits(
    config,
):
    """The compiled assembly's first two element groups (all nodes in the first half of the
    numbers, all in the second) are summed side by side: every element is in exactly one group,
    no CSR entry is written by both, and one thread or two give the same bits, equal to the
    NumPy reference's Jacobian to round-off."""
    mesh, x, _ = config
    body = build_body(mesh.reordered(), Material(1e5, 0.45, 50.0, LAWS["polynomial"]))
    x = np.asarray(body.mesh.points) * 1.01 + 1e-4 * np.sin(np.arange(3 * body.n_nodes)).reshape(-1, 3)
    eo, eb, to, tb = elastic.assembly_partition(body.edges, body.mesh.tets, body.n_nodes)
    assert np.array_equal(np.sort(eo), np.arange(len(body.edges)))
    assert np.array_equal(np.sort(to), np.arange(len(body.mesh.tets)))
    assert eb[1] > 0 and eb[2] > eb[1] and tb[1] > 0 and tb[2] > tb[1]  # both groups hold elements
    pattern = body._jacobian_pattern
    E = len(body.edges)
    written = []
    for g in (0, 1):
        edges = eo[eb[g] : eb[g + 1]]
        tets = to[tb[g] : tb[g + 1]]
        blocks = np.concatenate(
            [edges + q * E for q in range(4)] + [4 * E + 16 * tets + k for k in range(16)]
        )
        written.append(set(pattern.block_base[blocks].tolist()))  # a block's first entry marks it
    assert not written[0] & written[1]
    one = body.internal_jacobian(x, threads=1)
    assert _rel(one, ref.body_internal_jacobian(body, x)) < TOL
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("one Numba thread: the groups cannot run side by side")
    two = body.internal_jacobian(x, threads=2)
    assert np.array_equal(one.data, two.data)


@pytest.mark.parametrize("law", ["polynomial", "tanh"])
def test_a_large_body_sums_its_forces_in_the_assembly_order_on_any_threads(config, law, monkeypatch):
    """A body at or above ``PARTITIONED_MIN_NODES`` nodes (lowered here) sums its forces and energy
    in the assembly's order, its first two element groups side by side: equal to the NumPy
    reference (forces with and without dashpots, energy) to round-off, and the same bits on one
    thread or two. A law that is not a polynomial keeps the serial kernels."""
    from softgrasp.linalg.sparse import _Threads

    mesh, x, v = config
    body = build_body(mesh.reordered(), Material(1e5, 0.45, 50.0, LAWS[law]))
    assert body.damping_time > 0
    x = np.asarray(body.mesh.points) * 1.01 + 1e-4 * np.sin(np.arange(3 * body.n_nodes)).reshape(-1, 3)
    v = 0.05 * np.cos(np.arange(3 * body.n_nodes)).reshape(-1, 3)
    monkeypatch.setattr(elastic, "PARTITIONED_MIN_NODES", 1)
    calls = []
    real = elastic.partitioned_forces
    monkeypatch.setattr(elastic, "partitioned_forces", lambda *a, **k: calls.append(1) or real(*a, **k))
    want = (ref.body_internal_forces(body, x), ref.body_internal_forces(body, x, v), ref.body_internal_energy(body, x))
    results = []
    for threads in (1, 2):
        with _Threads(threads):
            results.append((body.internal_forces(x), body.internal_forces(x, v), body.internal_energy(x)))
    assert len(calls) == 6
    for got, ref_value in zip(results[0], want, strict=True):
        assert _rel(got, ref_value) < TOL
    if law != "polynomial":
        assert real(x, None, body._force_elements, body.material.law, body.kappa, body.barrier) is None
    if numba.config.NUMBA_NUM_THREADS >= 2:
        for one, two in zip(results[0], results[1], strict=True):
            assert np.array_equal(one, two)


def _forked_large_body_forces(finished_ok) -> None:
    """Evaluate a large body's forces on Numba's threads, fork, and check that the child gets the
    same forces (its ``backend.forked()`` says whether it took the serial kernels)."""
    import multiprocessing

    body = build_body(box(0.04, 3).reordered(), Material(1e5, 0.45, 50.0, LAWS["polynomial"]))
    x = np.asarray(body.mesh.points) * 1.01
    f = body.internal_forces(x)  # the parallel kernel, in the parent
    child = multiprocessing.get_context("fork").Process(target=_forces_in_child, args=(body, x, f))
    child.start()
    assert finished_ok(child)


def _forces_in_child(body, x, want) -> None:
    lost = numba.threading_layer() == "omp"
    if backend.forked() != lost or backend.compiled() == lost:
        raise SystemExit(2)
    got = body.internal_forces(x)
    if not np.abs(got - want).max() <= 1e-12 * np.abs(want).max():
        raise SystemExit(3)


@pytest.mark.skipif(not hasattr(__import__("os"), "fork"), reason="no fork on this platform")
def test_a_forked_child_sums_a_large_body_forces(monkeypatch, finished_ok):
    """A process forked after a large body's forces ran on Numba's threads (a script forking
    workers after planning) evaluates them in the child to the same values; with TBB as the
    threading layer (the default where it is installed) on the child's own threads."""
    monkeypatch.setattr(elastic, "PARTITIONED_MIN_NODES", 1)
    _forked_large_body_forces(finished_ok)


def _tbb_installed() -> bool:
    from importlib import metadata

    try:
        metadata.distribution("tbb")
    except metadata.PackageNotFoundError:
        return False
    return True


@pytest.mark.skipif(
    __import__("os").environ.get("NUMBA_THREADING_LAYER", "default") not in ("default", "tbb", "safe")
    or not _tbb_installed()
    or not __import__("sys").platform.startswith("linux"),
    reason="another threading layer chosen by the environment, TBB not installed, or not Linux",
)
def test_numba_threads_come_from_tbb_where_it_is_installed(monkeypatch):
    """softgrasp makes pip's TBB library loadable, so Numba's parallel kernels run on its
    fork-safe TBB layer rather than GNU OpenMP (whose threads a forked child cannot use)."""
    monkeypatch.setattr(elastic, "PARTITIONED_MIN_NODES", 1)
    body = build_body(box(0.04, 2).reordered(), Material(1e5, 0.45, 50.0, LAWS["polynomial"]))
    body.internal_forces(np.asarray(body.mesh.points))
    assert numba.threading_layer() == "tbb"


_OPENMP_FORK = """
import sys
sys.path.insert(0, {tests!r})
import numba, pytest
from softgrasp.physics import forces_compiled as elastic
import test_kernels, test_linsolve
elastic.PARTITIONED_MIN_NODES = 1
def finished_ok(child):
    child.join(60)
    alive = child.is_alive()
    if alive:
        child.kill()
    return not alive and child.exitcode == 0
test_kernels._forked_large_body_forces(finished_ok)
test_linsolve._multigrid_solve_then_fork(finished_ok)
print(numba.threading_layer())
"""


@pytest.mark.skipif(not hasattr(__import__("os"), "fork"), reason="no fork on this platform")
def test_under_openmp_a_forked_child_takes_the_serial_kernels():
    """With GNU OpenMP as the threading layer (``NUMBA_THREADING_LAYER=omp``: its threads do not
    survive a fork, and a parallel kernel in the child terminates it) the forked child knows
    (``backend.forked()``, ``backend.compiled()`` false) and takes the serial force kernels, SciPy's
    and pyamg's solver routines: a large body's forces the same, a multigrid solve converged, the
    child exits 0 (a parallel kernel there would terminate it, exit -15)."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    tests = str(Path(__file__).parent)
    env = {**os.environ, "NUMBA_THREADING_LAYER": "omp"}
    run = subprocess.run(
        [sys.executable, "-c", _OPENMP_FORK.format(tests=tests)],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    if "omp" not in run.stdout and "No threading layer could be loaded" in run.stderr:
        pytest.skip("no GNU OpenMP runtime for Numba here")
    assert run.returncode == 0, run.stderr[-2000:]
    assert run.stdout.split()[-1] == "omp"


def test_polynomial_coefficients_only_for_exact_types():
    assert elastic.polynomial_coefficients(Linear()) == (0.0, 0.0)
    assert elastic.polynomial_coefficients(Polynomial(a2=-0.4, a3=1.5)) == (-0.4, 1.5)
    assert elastic.polynomial_coefficients(ShiftedPolynomial(a3=0.5)) is None
    assert elastic.polynomial_coefficients(SoftTanh()) is None


# ------------------------------------------------------------------------------- contact
R_TIP = 0.008


def _tips_on(mesh, x, seed: int, depth: float, moving: bool = True) -> tuple[Fingertip, ...]:
    """Three fingertips pressed ``depth`` into the surface near random facets, off their centroids
    (so that contact patches straddle facet edges), moving and spinning (or at rest)."""
    rng = np.random.default_rng(seed)
    facets = mesh.facets
    tri = x[facets]
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    tips = []
    for k, f in enumerate(rng.choice(len(facets), 3, replace=False)):
        b = rng.dirichlet([1.0, 1.0, 1.0])
        q = b @ tri[f]
        tips.append(
            Fingertip(
                R_TIP,
                centre=q + (R_TIP - depth) * nrm[f],
                velocity=0.01 * rng.standard_normal(3) * moving,
                omega=rng.standard_normal(3) * moving,
                name=f"tip{k}",
            )
        )
    return tuple(tips)


@pytest.fixture(scope="module")
def contact_setup():
    """A perturbed sphere, its body, and positions/velocities (the fingertips are set per test)."""
    mesh = make_object("sphere", 0.014)[0]
    x, v = _perturbed(mesh, 21, 2e-4)
    body = build_body(mesh, Material(0.0793e6, 0.45, 45.0))
    return mesh, body, x, 0.01 * v


def _pairs_equal(fast, slow) -> None:
    assert len(slow) > 0
    assert np.array_equal(fast.finger, slow.finger) and np.array_equal(fast.facet, slow.facet)
    for name in ("bary", "point", "normal", "distance", "depth", "area", "facing"):
        assert _rel(getattr(fast, name), getattr(slow, name)) < TOL, name


def _state_equal(fast, slow) -> None:
    assert np.array_equal(fast.active, slow.active)
    for name in ("anchor", "offset", "slip", "memory"):
        a, b = getattr(fast, name), getattr(slow, name)
        assert np.abs(a - b).max() <= TOL * max(np.abs(b).max(), 1e-300), name


@pytest.mark.parametrize("closest", [False, True], ids=["paper", "closest"])
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_detect_agrees(contact_setup, closest, seed):
    mesh, _, x, _ = contact_setup
    tips = _tips_on(mesh, x, seed, 0.002)
    # and one whose centre projects just outside a facet (barycentric -0.004): for that facet the
    # contact point is the triangle's closest point, on an edge
    f = 7 * seed
    a, b, c = x[mesh.facets[f]]
    n = np.cross(b - a, c - a)
    q = -0.004 * a + 0.502 * b + 0.502 * c
    centres = np.array([t.centre for t in tips] + [q + 0.9 * R_TIP * n / np.linalg.norm(n)])
    radii = np.full(len(centres), R_TIP)
    index = FacetIndex.of(mesh)
    fast = detect(x, mesh.facets, centres, radii, closest=closest, index=index)
    slow = oracle_detect(x, mesh.facets, centres, radii, closest=closest, index=index)
    _pairs_equal(fast, slow)
    # The same pairs followed through a displacement (touching there or not), and found by the
    # k-d tree broad phase with the compiled narrow phase.
    from softgrasp.physics.fingertip.geometry import pair_geometry as follow

    x2 = x + 3e-4 * np.random.default_rng(seed).standard_normal(x.shape)
    _pairs_equal(
        follow(x2, mesh.facets, centres, radii, slow.finger, slow.facet, closest=closest),
        pair_geometry(x2, mesh.facets, centres, radii, slow.finger, slow.facet, closest=closest),
    )
    tree = detect(x, mesh.facets, centres, radii, closest=closest)
    order = np.lexsort((tree.facet, tree.finger))
    assert np.array_equal(tree.finger[order], slow.finger) and np.array_equal(tree.facet[order], slow.facet)
    assert _rel(tree.depth[order], slow.depth) < TOL
    assert set(slow.finger.tolist()) >= {0, 1, 2}  # the fourth may sit in a convex edge's blind spot
    if closest:  # the closest point on an edge is exercised
        mine = (slow.finger == 3) & (slow.facet == f)
        assert mine.any() and (slow.bary[mine] >= 0).all() and (slow.bary[mine] == 0).any()
        assert (slow.facing[mine] < 1).all()


RULES = {
    "patch": ContactParams(),
    "facet": ContactParams(rule="facet"),
    "hunt-crossley": ContactParams(damping="hunt-crossley"),
    "frictionless": ContactParams(mu=0.0),
    "given-ratio": ContactParams(tangential_ratio=0.5, min_depth_ratio=0.3),
}


@pytest.mark.parametrize("params", RULES.values(), ids=RULES.keys())
@pytest.mark.parametrize("shift", [1e-6, 2e-3], ids=["stick", "slip"])
@pytest.mark.parametrize("moving", [True, False], ids=["moving", "at-rest"])
def test_fingertip_forces_and_update_agree(contact_setup, params, shift, moving):
    """A state recorded at x0, then forces and update at x1 = x0 slid by ``shift`` [m] under the
    fingertips (continuing pairs with anchors, new pairs inheriting the finger's memory), at a
    later time (the fingertips have moved 10 um). At rest (no velocities) a slipping pair takes
    the capped stick force instead of Coulomb's sliding direction."""
    mesh, body, x0, v = contact_setup
    v = v if moving else np.zeros_like(v)
    tips = _tips_on(mesh, x0, 5, 0.002, moving)
    contacts = {"numba": FingertipContact(tips, params), "numpy": OracleFingertipContact(tips, params)}
    oc = contacts["numpy"]
    state = oc.update(body, x0, v, 0.0, oc.init_state(body, x0 + 0.5 * shift))
    assert state.active.sum() >= 3
    x1 = x0 + shift * np.array([1.0, -0.5, 0.2])
    t1 = 1e-3
    out = {}
    for name, fc in contacts.items():
        f = fc.forces(body, x1, v, t1, state)
        new = fc.update(body, x1, v, t1, state)
        out[name] = (f, new, fc.forces(body, x1, v, t1, new), fc.update(body, x1, -v, t1, new))
    fast, slow = out["numba"], out["numpy"]
    for k in (0, 2):
        assert _rel(fast[k], slow[k]) < TOL
    for k in (1, 3):
        _state_equal(fast[k], slow[k])
    # The cases are what they claim: the reference slips (or not) and has new and continuing pairs.
    ev = oc._evaluate(body, x1, v, t1, state, static=False)
    cont = state.active[ev.pairs.finger, ev.pairs.facet]
    assert cont.any()
    if params.mu > 0:
        assert ev.slipping.any() if shift > 1e-5 else (~ev.slipping).any()


@pytest.mark.parametrize("params", RULES.values(), ids=RULES.keys())
@pytest.mark.parametrize("shift", [1e-6, 2e-3], ids=["stick", "slip"])
def test_static_and_pinned_forces_agree(contact_setup, params, shift):
    """The static solver's residual (the touching pairs at rest) and its exact Newton product (a
    pinned pair set followed through a displacement, pairs out of contact there included) in one
    compiled call each, against the NumPy reference; moving fingertips' velocities do not enter."""
    mesh, body, x0, v = contact_setup
    tips = _tips_on(mesh, x0, 5, 0.002, moving=True)
    contacts = {"numba": FingertipContact(tips, params), "numpy": OracleFingertipContact(tips, params)}
    fc = oc = contacts["numpy"]
    state = oc.update(body, x0, v, 0.0, oc.init_state(body, x0 + 0.5 * shift))
    x1 = x0 + shift * np.array([1.0, -0.5, 0.2])
    t1 = 1e-3
    # A displacement that moves part of the pinned set out of contact (and changes the rest).
    rng = np.random.default_rng(3)
    x2 = x1 + 3e-4 * rng.standard_normal(x1.shape)
    out = {}
    for name, contact in contacts.items():
        pinned = contact.pinned_static_forces(body, x1, t1, state)
        out[name] = (contact.static_forces(body, x1, t1, state), pinned(x1), pinned(x2))
    for fast, slow in zip(out["numba"], out["numpy"], strict=True):
        assert np.abs(slow).max() > 0
        assert _rel(fast, slow) < TOL
    assert _rel(out["numpy"][1], out["numpy"][0]) < 1e-12  # pinned at the pairs' own state: the same
    # The cases are what they claim: some pinned pairs leave contact at x2; friction slips (or not).
    ref = fc.pairs(body, x1, t1)
    tips = fc.centres(t1), fc._radii()
    moved = pair_geometry(x2, mesh.facets, *tips, ref.finger, ref.facet, closest=True)
    ev = oc._evaluate(body, x1, None, t1, state, static=True)
    if params.rule == "patch":
        assert (moved.depth <= 0).any() and (moved.depth > 0).any()
    if params.mu > 0:
        assert ev.slipping.any() if shift > 1e-5 else (~ev.slipping).any()


def test_fingertip_forces_agree_without_contact(contact_setup):
    mesh, body, x, v = contact_setup
    far = Fingertip(R_TIP, centre=x.max(axis=0) + 0.05)
    for fc in (FingertipContact((far,)), OracleFingertipContact((far,))):
        state = fc.init_state(body, x)
        assert not fc.forces(body, x, v, 0.0, state).any()
        assert not fc.update(body, x, v, 0.0, state).active.any()


@pytest.mark.parametrize("method", ["rk4", "semi-implicit"])
def test_trajectories_agree(contact_setup, method):
    """Two pipelines, one trajectory: 40 explicit steps of the sphere on the table with a fingertip
    pressing on its top (contact, friction, dampers active), compiled versus reference."""
    mesh, body, _, _ = contact_setup
    x = np.asarray(mesh.points)
    top = int(np.argmax(x[mesh.facets].mean(axis=1)[:, 2]))
    a, b, c = x[mesh.facets[top]]
    n = np.cross(b - a, c - a)
    tip = Fingertip(
        R_TIP, centre=(a + b + c) / 3 + (R_TIP - 0.002) * n / np.linalg.norm(n), velocity=[0, 0, -0.01]
    )
    table = PlaneContact(Plane([0, 0, 0], [0, 0, 1]), mu=0.5, name="table")
    scene = Scene(body, (table, FingertipContact((tip,))))
    s0 = scene.initial_state()
    dt = stable_time_step(scene, method)
    out = {
        "numba": simulate(scene, s0, 40 * dt, method=method, dt=dt),
        "numpy": simulate(oracle_scene(scene), s0, 40 * dt, method=method, dt=dt),
    }
    fast, slow = out["numba"], out["numpy"]
    assert len(scene.interactions[1].pairs(body, slow.x, slow.t)) > 0
    assert _rel(fast.x - s0.x, slow.x - s0.x) < TOL
    assert _rel(fast.v, slow.v) < TOL
    for a_state, b_state in zip(fast.contacts, slow.contacts, strict=True):
        assert np.array_equal(a_state.active, b_state.active)


_WARM_SCRIPT = """
import json, numba
from numba.core.registry import CPUDispatcher
from softgrasp.cli import warm
from softgrasp.physics import forces_compiled as elastic, springs, volume
from softgrasp.physics.fingertip import compiled as contact, detect, forces, friction
from softgrasp.physics.body import build_body
from softgrasp.grasp.planner import PlanConfig, plan_grasp
from softgrasp.model.objects import make_object

def signatures():
    return {f"{m.__name__}.{k}": sorted(map(str, v.signatures)) for m in (elastic, springs, volume, contact, detect, forces, friction)
            for k, v in vars(m).items() if isinstance(v, CPUDispatcher)}

warm.warm_up()
after_warm_up = signatures()
mesh, material, mass = make_object("sphere")
plan_grasp(build_body(mesh, material, mass=mass), PlanConfig(hand=None, hold_time=0.05))
print(json.dumps({"warm": after_warm_up, "plan": signatures()}))
"""


def test_warm_up_loads_every_kernel_a_plan_calls():
    """In a fresh interpreter, the warm-up's tiny solve loads every compiled kernel, with every
    argument-type signature, that a whole plan of the default sphere then calls: the plan adds
    no signature (it would otherwise load or compile one itself)."""
    import json
    import subprocess
    import sys

    run = subprocess.run([sys.executable, "-c", _WARM_SCRIPT], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    got = json.loads(run.stdout.strip().splitlines()[-1])
    used = {k: v for k, v in got["plan"].items() if v}
    assert len(used) >= 6  # the springs, volumes, their blocks, inverted tets, detection, forces
    missing = {k: sorted(set(v) - set(got["warm"].get(k, []))) for k, v in used.items()}
    assert not any(missing.values()), missing
