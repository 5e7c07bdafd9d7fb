"""The fused compiled stepper (:mod:`softgrasp.sim.fused.step`) against the per-step path of
``simulate`` (RK4) on the compiled kernels and the NumPy reference (the oracles of
``tests/oracles``: :func:`oracles.contact.oracle_scene`'s body and fingertips, the planes of
:mod:`oracles.planes`): same trajectory, contact states and contact forces (to 1e-8), same
callbacks and progress reports, same blow-up errors, the same result on one thread or two; free
fall to round-off; the compiled kernels' cache keyed by the sources they inline."""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest

from oracles import planes as oracle_planes
from oracles.contact import oracle_scene
from softgrasp.errors import SimulationUnstable
from softgrasp.experiments.indentation import surface_height
from softgrasp.model.material import Material, Tabulated
from softgrasp.model.mesh import box
from softgrasp.model.objects import make_object
from softgrasp.physics.body import build_body
from softgrasp.physics.fingertip.contact import FingertipContact
from softgrasp.physics.fingertip.params import Fingertip
from softgrasp.physics.planes import Plane, PlaneContact
from softgrasp.sim import Scene, simulate, stable_time_step
from softgrasp.sim.explicit import fused_unsupported, make_integrator
from softgrasp.sim.stability import BlowupMonitor

pytest.importorskip("numba")
from softgrasp.sim.fused import body as fused_body  # noqa: E402 - needs numba
from softgrasp.sim.fused import contacts, step  # noqa: E402

TOL = 1e-8
RUBBER = Material(0.0793e6, 0.45, 45.5)


def _rel(a: np.ndarray, b: np.ndarray) -> float:
    scale = float(np.abs(b).max())
    return float(np.abs(a - b).max()) / scale if scale > 0 else float(np.abs(a).max())


@pytest.fixture(scope="module")
def pressed():
    """The bench_dynamic scene on a coarse mesh: the rubber sphere (549 nodes) on the table (mu 0.5),
    a rigid R = 8 mm fingertip pressed 2 mm into its top and moving down at 5 mm/s; the sphere starts
    sliding sideways so that the table's friction is loaded."""
    mesh, mat, mass = make_object("sphere", 0.014)
    body = build_body(mesh, mat, mass=mass)
    x = np.asarray(mesh.points)
    _, f = surface_height(x, mesh.facets, mesh.centroid[:2])
    xy = x[mesh.facets[f]].mean(axis=0)[:2]
    zs, _ = surface_height(x, mesh.facets, xy)
    tip = Fingertip(0.008, centre=[xy[0], xy[1], zs + 0.006], velocity=[0.0, 0.0, -0.005])
    table = PlaneContact(Plane([0, 0, 0], [0, 0, 1]), mu=0.5, name="table")
    scene = Scene(body, (table, FingertipContact((tip,))))
    v0 = np.tile([0.02, -0.01, 0.0], (body.n_nodes, 1))
    return scene, scene.initial_state(v=v0)


def _reference(scene):
    """``scene`` on the NumPy oracles: its body and fingertips (:func:`oracle_scene`) and its planes
    (:class:`OraclePlaneContact`)."""
    reference = oracle_scene(scene)
    inters = tuple(
        oracle_planes.OraclePlaneContact(**{f.name: getattr(i, f.name) for f in dataclasses.fields(i)})
        if type(i) is PlaneContact
        else i
        for i in reference.interactions
    )
    return dataclasses.replace(reference, interactions=inters)


def _contact_forces(scene, state) -> list[np.ndarray]:
    """The contact forces of ``state`` by the NumPy reference (the oracles)."""
    reference = _reference(scene)
    return [
        inter.forces(reference.body, state.x, state.v, state.t, st)
        for inter, st in zip(reference.interactions, state.contacts, strict=True)
    ]


def _assert_same(scene, s0, fast, slow) -> None:
    assert fast.t == pytest.approx(slow.t, rel=1e-15)
    assert _rel(fast.x - s0.x, slow.x - s0.x) < TOL
    assert _rel(fast.v, slow.v) < TOL
    for a, b in zip(fast.contacts, slow.contacts, strict=True):
        assert type(a) is type(b)
        assert np.array_equal(a.active, b.active)
        for name in ("anchor", "offset", "slip", "memory"):
            if hasattr(b, name):
                assert np.abs(getattr(a, name) - getattr(b, name)).max() <= TOL * max(
                    np.abs(getattr(b, name)).max(), 1e-6
                ), name
    for fa, fb in zip(_contact_forces(scene, fast), _contact_forces(scene, slow), strict=True):
        assert _rel(fa, fb) < TOL


def test_fused_path_is_chosen_only_when_supported(pressed):
    scene, _ = pressed
    rk4 = make_integrator("rk4")
    assert fused_unsupported(scene, rk4) is None
    assert "semi-implicit" in fused_unsupported(scene, make_integrator("semi-implicit"))
    assert "dopri" in fused_unsupported(scene, make_integrator("dopri"))
    tabulated = build_body(
        box(0.02, 1), Material(1e5, 0.45, 50.0, law=Tabulated([0.05, 0.1, 0.2], [5e3, 1e4, 2.1e4]))
    )
    assert "not a polynomial" in fused_unsupported(Scene(tabulated), rk4)
    with pytest.raises(ValueError, match="fused stepper cannot run"):
        simulate(scene, scene.initial_state(), 1e-5, method="semi-implicit", fused=True)
    # the NumPy oracles' interactions: ones the fused loop does not know
    assert "OracleFingertipContact" in fused_unsupported(oracle_scene(scene), rk4)
    reference = _reference(scene)
    assert "OraclePlaneContact" in fused_unsupported(reference, rk4)
    with pytest.raises(ValueError, match="fused stepper cannot run"):
        simulate(reference, scene.initial_state(), 1e-5, method="rk4", fused=True)
    with pytest.raises(ValueError, match="runs rk4"):
        x = scene.body.mesh.points
        step.FusedStepper(scene.body, [], [], None, None, x, 0 * x, 0.0, method="semi-implicit")


@pytest.mark.parametrize("method", ["rk4"])
def test_fused_agrees_with_per_step_and_reference(pressed, method):
    """200 steps with the fingertip touching, the table's friction loaded and all dampers on: the
    fused loop, the per-step loop on the compiled kernels and the NumPy reference agree."""
    scene, s0 = pressed
    dt = stable_time_step(scene, method)
    T = 200 * dt
    fused = simulate(scene, s0, T, method=method, dt=dt)
    per_step = simulate(scene, s0, T, method=method, dt=dt, fused=False)
    reference = simulate(_reference(scene), s0, T, method=method, dt=dt, fused=False)
    fingers = scene.interactions[1]
    assert len(fingers.pairs(scene.body, fused.x, fused.t)) > 0
    table_state = fused.contacts[0]
    assert table_state.active.sum() > 0
    # friction is loaded: touching nodes pulled off their anchors, some up to the Coulomb limit
    f_table = _contact_forces(scene, fused)[0]
    assert np.abs(f_table[:, :2]).max() > 1e-3 * np.abs(f_table[:, 2]).max()
    _assert_same(scene, s0, fused, per_step)
    _assert_same(scene, s0, fused, reference)


def test_callbacks_and_progress_match_per_step(pressed):
    scene, s0 = pressed
    dt = stable_time_step(scene, "rk4")
    runs = {}
    for fused in (True, False):
        calls, reports = [], []
        out = simulate(
            scene, s0, 57 * dt, method="rk4", dt=dt, callback=calls.append, every=10,
            progress=reports.append, fused=fused,
        )  # fmt: skip
        runs[fused] = (out, calls, reports)
    (a, ca, pa), (b, cb, pb) = runs[True], runs[False]
    assert [s.t for s in ca] == pytest.approx([s.t for s in cb], rel=1e-14, abs=1e-18)
    assert len(ca) == 7  # the initial state, steps 10, 20, ..., 50, and the final state
    for sa, sb in zip(ca, cb, strict=True):
        assert _rel(sa.v, sb.v) < TOL
    # the callbacks received independent snapshots
    assert not np.shares_memory(ca[1].x, ca[2].x)
    assert ca[1].t < ca[2].t and not np.array_equal(ca[1].x, ca[2].x)
    assert len(pa) == len(pb) and pa[-1] == 1.0
    assert np.allclose(pa, pb, atol=2.0 / 57)
    _assert_same(scene, s0, a, b)


def test_free_fall_of_the_centroid_to_round_off():
    """No contact: internal forces sum to zero, so the centroid falls as RK4 integrates a constant
    acceleration: exactly, x(t) = x_0 + v_0 t + g t^2 / 2, to round-off."""
    body = build_body(box(0.04, 2), RUBBER, damping_ratio=0.1)
    scene = Scene(body)
    rng = np.random.default_rng(3)
    v0 = np.array([0.1, -0.2, 0.3])
    s0 = scene.initial_state(
        body.mesh.points + 1e-4 * rng.standard_normal(body.mesh.points.shape), np.tile(v0, (body.n_nodes, 1))
    )
    h = stable_time_step(scene, "rk4")
    n = 400
    assert fused_unsupported(scene, make_integrator("rk4")) is None
    out = simulate(scene, s0, n * h, method="rk4", dt=h)
    m = body.mass / body.total_mass
    com0, com = m @ s0.x, m @ out.x
    g = np.asarray(body.gravity)
    t = out.t
    assert t == pytest.approx(n * h, rel=1e-14)
    assert np.abs(com - (com0 + v0 * t + 0.5 * g * t * t)).max() < 1e-12 * max(1.0, np.abs(com).max())
    assert np.abs(m @ out.v - (v0 + g * t)).max() < 1e-12


@pytest.mark.parametrize(
    ("method", "nu", "factor", "check_every", "reason"),
    [
        ("rk4", 0.45, 10, 10, "energy grew"),
        ("rk4", 0.45, 12, 3, "inverted"),
        ("rk4", 0.45, 14, 10, "non-finite"),
        ("rk4", 0.25, 12, 3, "inverted"),  # nu = 1/4: no volume term (kappa = 0)
    ],
    ids=["rk4-energy", "rk4-inverted", "rk4-non-finite", "no-volume-term-inverted"],
)
def test_blow_up_raises_the_same_error(method, nu, factor, check_every, reason):
    """A step far beyond the stable bound (check_dt=False) blows up; the fused loop stops at the
    same step with the same SimulationUnstable (reason, time, step, first inverted tet, suggested
    step). How many more tets are inverted at that step, in a state tens of times past the stable
    step, is round-off: the compiled kernel and NumPy sum in other orders (61 or 62 of them)."""
    body = build_body(box(0.04, 2), Material(RUBBER.E, nu, RUBBER.density))
    scene = Scene(body, (PlaneContact(Plane([0, 0, 0], [0, 0, 1]), mu=0.5, name="table"),))
    rng = np.random.default_rng(11)
    s0 = scene.initial_state(body.mesh.points + 1e-4 * rng.standard_normal(body.mesh.points.shape))
    dt = factor * stable_time_step(scene, method)
    errors = {}
    for fused in (True, False):
        with pytest.raises(SimulationUnstable, match=reason) as err:
            simulate(
                scene,
                s0,
                3000 * dt,
                method=method,
                dt=dt,
                check_dt=False,
                check_every=check_every,
                fused=fused,
            )
        errors[fused] = err.value
    more = re.compile(r" and (\d+) more inverted")
    fused, stepped = (more.sub(" and N more inverted", str(errors[f])) for f in (True, False))
    assert fused == stepped
    counts = [int(m.group(1)) for e in errors.values() if (m := more.search(str(e)))]
    assert len(counts) in (0, 2) and (not counts or abs(counts[0] - counts[1]) <= 0.05 * max(counts))
    assert errors[True].suggested_dt == pytest.approx(0.5 * stable_time_step(scene, method))
    assert "simulation unstable at t = " in str(errors[True])


def test_energy_bookkeeping_with_plates_doing_work():
    # Energy enters through a moving plate: the monitor's work integral (kept by the compiled loop)
    # must absorb it, with the checks at every step.
    body = build_body(box(0.05, 2), RUBBER)
    plate = PlaneContact(Plane([0, 0, 0.05], [0, 0, -1], velocity=[0, 0, -1.0]), mu=0.5, name="top")
    table = PlaneContact(Plane([0, 0, 0], [0, 0, 1]), mu=0.5, name="table")
    scene = Scene(body, (table, plate))
    s0 = scene.initial_state()
    dt = stable_time_step(scene, "rk4")
    fast = simulate(scene, s0, 0.004, method="rk4", dt=dt, check_every=1)
    slow = simulate(scene, s0, 0.004, method="rk4", dt=dt, check_every=1, fused=False)
    _assert_same(scene, s0, fast, slow)
    assert fast.x[:, 2].max() < 0.05 - 0.003


def test_fused_stepper_chunks_compose(pressed):
    """Stepping in chunks of any length gives the same trajectory as one long chunk."""
    scene, s0 = pressed
    fingers = scene.interactions[1]
    dt = stable_time_step(scene, "rk4")

    def make():
        return step.FusedStepper(
            scene.body, [scene.interactions[0]], [s0.contacts[0]], fingers, s0.contacts[1], s0.x, s0.v, s0.t
        )

    one, parts = make(), make()
    assert one.advance(30, dt) == 30
    for n in (1, 2, 7, 20):
        parts.advance(n, dt)
    assert parts.t == one.t
    assert np.array_equal(parts.x, one.x) and np.array_equal(parts.v, one.v)
    assert np.array_equal(parts.finger_state(s0.contacts[1]).anchor, one.finger_state(s0.contacts[1]).anchor)


def test_the_near_list_holds_every_surface_node_the_full_scan_would_find(pressed):
    """The fingertip broad phase scans a Verlet list of surface nodes (contacts.finger_reach): with the
    fingertip sweeping 40 mm across the sphere and the nodes drifting and jittering, every surface
    node within R + margin of the centre (what the scan over all of them finds) is in the list at
    every call, the list is renewed on the way, and it is much shorter than the surface."""
    scene, s0 = pressed
    st = step.FusedStepper(
        scene.body, [scene.interactions[0]], [s0.contacts[0]], scene.interactions[1], s0.contacts[1], s0.x,
        s0.v, s0.t,
    )  # fmt: skip
    fg = list(st._fg)
    fg[7] = np.array([[40.0, 10.0, -5.0]])  # the centre's velocity [m/s]: 41.5 mm in 1 ms
    fg = tuple(fg)
    _, _, _, _, centres, x_ref, track, _, near = st._work
    boundary, radius = fg[2], fg[9][0]
    rng = np.random.default_rng(7)
    x = st.x.copy()
    renewals, lengths = 0, []
    for k in range(400):
        t = k * 2.5e-6
        x[:, :3] += 2e-5 * np.array([1.0, -0.5, 0.2]) + 2e-5 * rng.standard_normal((len(x), 3))
        u2 = float(((x[:, :3] - x_ref[:, :3]) ** 2).sum(axis=1).max())
        track[1] = max(track[1], u2)  # as the node pass keeps it
        before = track[0], track[2]
        margin, n = contacts.finger_reach(x, t, fg, x_ref, track, near, centres)
        renewals += (track[0], track[2]) != before or track[1] == 0.0
        listed = set(near[:n].tolist())
        assert len(listed) == n
        d = np.linalg.norm(x[boundary, :3] - centres[0], axis=1)
        assert set(boundary[d < radius + margin].tolist()) <= listed
        lengths.append(n)
    assert renewals >= 3 and max(lengths) < 0.5 * len(boundary)


def test_steppers_share_a_body_packing_that_does_not_keep_the_body():
    """A body is packed for the kernels once (pack_body's tuple kept per body); the cache holds the
    body weakly: gone with its last stepper."""
    import gc
    import weakref

    body = build_body(box(0.03, 2), RUBBER)
    scene = Scene(body)
    s0 = scene.initial_state()
    a = step.FusedStepper(body, [], [], None, None, s0.x, s0.v, s0.t)
    b = step.FusedStepper(body, [], [], None, None, s0.x, s0.v, s0.t)
    assert a._body is b._body
    assert body in fused_body._PACKED
    gone = weakref.ref(body)
    del a, b, body, scene
    gc.collect()
    assert gone() is None  # the cache did not keep it (its entry went with it)


@pytest.mark.parametrize("method", ["rk4"])
def test_threads_do_not_change_the_result(pressed, method):
    """The body forces are summed from the same parts whether one thread or two (Numba's) compute
    them, so the trajectory, the friction states and the monitor's bookkeeping are bit-for-bit the
    same."""
    scene, s0 = pressed
    fingers = scene.interactions[1]
    dt = stable_time_step(scene, method)
    runs = []
    for threads in (1, 2):
        monitor = BlowupMonitor(scene, s0, method, check_every=3)
        st = step.FusedStepper(
            scene.body, [scene.interactions[0]], [s0.contacts[0]], fingers, s0.contacts[1], s0.x, s0.v, s0.t,
            monitor, method=method,
        )  # fmt: skip
        st.threads = threads
        for n in (1, 13, 26):  # chunks: the threads start and stop again
            assert st.advance(n, dt) == n
        runs.append(st)
    one, two = runs
    assert two.t == one.t and np.array_equal(one.x, two.x) and np.array_equal(one.v, two.v)
    assert np.array_equal(one.pl_anchor, two.pl_anchor)
    assert np.array_equal(one.finger_state(s0.contacts[1]).anchor, two.finger_state(s0.contacts[1]).anchor)
    assert one.monitor.steps == two.monitor.steps == 40
    assert one.monitor.balance == two.monitor.balance
    assert one.finger_state(s0.contacts[1]).active.any()  # the fingertip touches


@pytest.mark.parametrize(
    ("nu", "factor", "check_every", "status"),
    [
        (0.45, 10, 10, step.STATUS_ENERGY),
        (0.45, 12, 3, step.STATUS_INVERTED),
        (0.45, 14, 10**6, step.STATUS_NONFINITE),
    ],
    ids=["energy", "inverted", "non-finite"],
)
def test_two_threads_stop_at_the_same_failure(nu, factor, check_every, status):
    """A blow-up (steps far beyond the stable bound) stops the two threads at the same step, with
    the same failure and state, as one thread."""
    body = build_body(box(0.04, 2), Material(RUBBER.E, nu, RUBBER.density))
    table = PlaneContact(Plane([0, 0, 0], [0, 0, 1]), mu=0.5, name="table")
    scene = Scene(body, (table,))
    rng = np.random.default_rng(11)
    s0 = scene.initial_state(body.mesh.points + 1e-4 * rng.standard_normal(body.mesh.points.shape))
    dt = factor * stable_time_step(scene, "rk4")
    runs = []
    for threads in (1, 2):
        monitor = BlowupMonitor(scene, s0, "rk4", check_every=check_every)
        st = step.FusedStepper(body, [table], [s0.contacts[0]], None, None, s0.x, s0.v, s0.t, monitor)
        st.threads = threads
        taken = st.advance(3000, dt)
        assert 0 < taken < 3000 and st.failure is not None and st.failure.status == status
        runs.append((taken, st))
    (n1, one), (n2, two) = runs
    assert n1 == n2 and one.failure == two.failure and one.monitor.steps == two.monitor.steps
    assert np.array_equal(one.x, two.x, equal_nan=True)


def test_fused_threads_follow_the_thread_setting_not_the_load(monkeypatch):
    """The fused stepper's thread count is the one thread setting, capped at the body's parts:
    never a reading of how busy the machine is."""
    from softgrasp.linalg import threads
    from softgrasp.sim.fused.run import fused_threads

    monkeypatch.setattr(threads, "_fixed", None)
    monkeypatch.setattr(threads, "cores", lambda: 8)
    assert fused_threads() == step.PARTS
    monkeypatch.setattr(threads, "cores", lambda: 1)
    assert fused_threads() == 1
    monkeypatch.setattr(threads, "_fixed", 2)
    assert fused_threads() == 2
    monkeypatch.setattr(threads, "_fixed", 1)
    assert fused_threads() == 1


def test_the_kernels_cache_is_keyed_by_every_source_they_inline():
    """Numba's cache checks only a kernel's own file; the fused kernels' index keys also hold the
    digest of every module whose compiled functions they call (among jitcache.KERNEL_MODULES): an
    edit of one of those gives another key, so the kernels compile afresh instead of running stale
    code."""
    import ast
    import importlib.util
    import pathlib

    from softgrasp import jitcache
    from softgrasp.sim.fused import cache, monitor, rk4

    sources = list(pathlib.Path(cache.__file__).parent.glob("*.py"))
    sources += [pathlib.Path(importlib.util.find_spec(m).origin) for m in jitcache.KERNEL_MODULES]
    called = set()
    for path in sources:  # the kernels' modules and the modules they call, one level further
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("softgrasp."):
                module = __import__(node.module, fromlist=["_"])
                names = [getattr(module, a.name, None) for a in node.names]
                if any(hasattr(f, "py_func") for f in names):  # a compiled function
                    called.add(node.module)
    assert called <= set(jitcache.KERNEL_MODULES)
    kernels = (rk4.advance, rk4.forces_at, fused_body.body_forces, contacts.finger_step, monitor.after_step)
    for kernel in kernels:
        assert isinstance(kernel._cache, jitcache.SourceKeyedCache)
        assert kernel._cache.digest == jitcache.SOURCE_DIGEST == jitcache.source_digest()
    keyed = jitcache.SourceKeyedCache(rk4.advance.py_func)
    other = jitcache.SourceKeyedCache(rk4.advance.py_func, digest="0" * 64)
    sig, codegen = ("a signature",), rk4.advance.targetctx.codegen()
    assert keyed._index_key(sig, codegen) != other._index_key(sig, codegen)
    assert keyed._index_key(sig, codegen)[:-1] == other._index_key(sig, codegen)[:-1]
