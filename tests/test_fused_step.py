"""The fused compiled stepper (:mod:`softgrasp.sim.fused.step`) against the per-step path of
``simulate`` (semi-implicit Euler and RK4) and the NumPy reference: same trajectory, contact states
and contact forces (to 1e-8), same callbacks and progress reports, same blow-up errors, the same
result on one thread or two; and free fall to round-off."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from oracles.contact import oracle_scene

from softgrasp.physics.body import build_body
from softgrasp.physics.fingertip.params import Fingertip
from softgrasp.physics.fingertip.contact import FingertipContact
from softgrasp.errors import SimulationUnstable
from softgrasp.experiments.indentation import surface_height
from softgrasp.model.material import Material, Tabulated
from softgrasp.model.mesh import box
from softgrasp.model.objects import make_object
from softgrasp.physics.planes import Plane, PlaneContact
from softgrasp.sim import Scene, simulate, stable_time_step
from softgrasp.sim.explicit import fused_unsupported, make_integrator
from softgrasp.sim.stability import BlowupMonitor

pytest.importorskip("numba")
from softgrasp.sim.fused import step  # noqa: E402 - needs numba

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


def _contact_forces(scene, state) -> list[np.ndarray]:
    reference = oracle_scene(scene)
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
    semi = make_integrator("semi-implicit")
    assert fused_unsupported(scene, semi) is None
    assert fused_unsupported(scene, make_integrator("rk4")) is None
    assert "dopri" in fused_unsupported(scene, make_integrator("dopri"))
    tabulated = build_body(
        box(0.02, 1), Material(1e5, 0.45, 50.0, law=Tabulated([0.05, 0.1, 0.2], [5e3, 1e4, 2.1e4]))
    )
    assert "not a polynomial" in fused_unsupported(Scene(tabulated), semi)
    reference = oracle_scene(scene)  # an interaction the fused loop does not know
    assert "OracleFingertipContact" in fused_unsupported(reference, semi)
    with pytest.raises(ValueError, match="fused stepper cannot run"):
        simulate(reference, scene.initial_state(), 1e-5, method="semi-implicit", fused=True)


@pytest.mark.parametrize("method", ["semi-implicit", "rk4"])
@pytest.mark.parametrize("blocks", [True, False])
def test_fused_agrees_with_per_step_and_reference(pressed, method, blocks, monkeypatch):
    """200 steps with the fingertip touching, the table's friction loaded and all dampers on: the
    fused loop (its body forces on the block kernels and on the scalar loops), the per-step loop on
    the compiled kernels and the NumPy reference agree."""
    scene, s0 = pressed
    dt = stable_time_step(scene, method)
    T = 200 * dt
    monkeypatch.setattr(step, "BLOCKS_DEFAULT", blocks)
    fused = simulate(scene, s0, T, method=method, dt=dt)
    per_step = simulate(scene, s0, T, method=method, dt=dt, fused=False)
    reference = simulate(oracle_scene(scene), s0, T, method=method, dt=dt)
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
    dt = stable_time_step(scene, "semi-implicit")
    runs = {}
    for fused in (True, False):
        calls, reports = [], []
        out = simulate(
            scene, s0, 57 * dt, method="semi-implicit", dt=dt, callback=calls.append, every=10,
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
    """No contact: internal forces sum to zero, so the centroid falls exactly as the semi-implicit
    Euler recursion of g: x_n = x_0 + v_0 t_n + g h^2 n (n + 1) / 2 (g t^2 / 2 plus the method's
    O(h) term g h t / 2)."""
    body = build_body(box(0.04, 2), RUBBER, damping_ratio=0.1)
    scene = Scene(body)
    rng = np.random.default_rng(3)
    v0 = np.array([0.1, -0.2, 0.3])
    s0 = scene.initial_state(
        body.mesh.points + 1e-4 * rng.standard_normal(body.mesh.points.shape), np.tile(v0, (body.n_nodes, 1))
    )
    h = stable_time_step(scene, "semi-implicit")
    n = 400
    assert fused_unsupported(scene, make_integrator("semi-implicit")) is None
    out = simulate(scene, s0, n * h, method="semi-implicit", dt=h)
    m = body.mass / body.total_mass
    com0, com = m @ s0.x, m @ out.x
    g = np.asarray(body.gravity)
    expected = com0 + v0 * n * h + g * h * h * n * (n + 1) / 2
    assert np.abs(com - expected).max() < 1e-12 * max(1.0, np.abs(com).max())
    assert np.abs(m @ out.v - (v0 + g * n * h)).max() < 1e-12
    t = n * h
    assert np.abs(com - (com0 + v0 * t + 0.5 * g * t * t)).max() <= 0.5 * np.linalg.norm(g) * h * t * 1.001


@pytest.mark.parametrize(
    ("method", "nu", "factor", "check_every", "reason"),
    [
        ("semi-implicit", 0.45, 8, 10, "energy grew"),
        ("semi-implicit", 0.45, 12, 3, "inverted"),
        ("semi-implicit", 0.45, 30, 10**6, "non-finite"),
        ("semi-implicit", 0.25, 12, 3, "inverted"),  # nu = 1/4: no volume term (kappa = 0)
        ("rk4", 0.45, 10, 10, "energy grew"),
        ("rk4", 0.45, 14, 10, "non-finite"),
    ],
    ids=[
        "semi-implicit-energy",
        "semi-implicit-inverted",
        "semi-implicit-non-finite",
        "no-volume-term-inverted",
        "rk4-energy",
        "rk4-non-finite",
    ],
)
def test_blow_up_raises_the_same_error(method, nu, factor, check_every, reason):
    """A step far beyond the stable bound (check_dt=False) blows up; the fused loop stops at the
    same step with the same SimulationUnstable (reason, time, step, suggested step)."""
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
    assert str(errors[True]) == str(errors[False])
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
    dt = stable_time_step(scene, "semi-implicit")
    fast = simulate(scene, s0, 0.004, method="semi-implicit", dt=dt, check_every=1)
    slow = simulate(scene, s0, 0.004, method="semi-implicit", dt=dt, check_every=1, fused=False)
    _assert_same(scene, s0, fast, slow)
    assert fast.x[:, 2].max() < 0.05 - 0.003


def test_fused_stepper_chunks_compose(pressed):
    """Stepping in chunks of any length gives the same trajectory as one long chunk."""
    scene, s0 = pressed
    fingers = scene.interactions[1]
    dt = stable_time_step(scene, "semi-implicit")

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
    """The fingertip broad phase scans a Verlet list of surface nodes (step._finger_reach): with the
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
    _, _, _, _, centres, x_ref, track, _, _, near = st._work
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
        margin, n = step._finger_reach(x, t, fg, x_ref, track, near, centres)
        renewals += (track[0], track[2]) != before or track[1] == 0.0
        listed = set(near[:n].tolist())
        assert len(listed) == n
        d = np.linalg.norm(x[boundary, :3] - centres[0], axis=1)
        assert set(boundary[d < radius + margin].tolist()) <= listed
        lengths.append(n)
    assert renewals >= 3 and max(lengths) < 0.5 * len(boundary)


def test_the_leader_takes_the_smaller_share_only_for_semi_implicit_steps(pressed):
    """The uneven split pays where the leader does the fingertips beside its part (semi-implicit
    on two threads); RK4's stages keep even parts."""
    scene, s0 = pressed
    args = (scene.body, [scene.interactions[0]], [s0.contacts[0]], scene.interactions[1], s0.contacts[1])
    semi = step.FusedStepper(*args, s0.x, s0.v, s0.t, method="semi-implicit")
    rk4 = step.FusedStepper(*args, s0.x, s0.v, s0.t, method="rk4")
    assert semi._body[14] < 0.5 and rk4._body[14] == 0.5


def test_steppers_share_a_body_packing_that_does_not_keep_the_body():
    """A body is packed for the kernels once (pack_body's tuple kept per body and share); the
    cache holds the body weakly: gone with its last stepper."""
    import gc
    import weakref

    body = build_body(box(0.03, 2), RUBBER)
    scene = Scene(body)
    s0 = scene.initial_state()
    a = step.FusedStepper(body, [], [], None, None, s0.x, s0.v, s0.t)
    b = step.FusedStepper(body, [], [], None, None, s0.x, s0.v, s0.t)
    assert a._body is b._body and a._body[14] == 0.5  # no fingertips: even parts
    assert body in step._PACKED
    gone = weakref.ref(body)
    del a, b, body, scene
    gc.collect()
    assert gone() is None  # the cache did not keep it (its entry went with it)


@pytest.mark.parametrize("method", ["semi-implicit", "rk4"])
def test_threads_do_not_change_the_result(pressed, method):
    """The body forces are summed from the same parts whether one thread or two compute them (two
    threads meeting on flags for semi-implicit steps, Numba's threads for RK4), so the trajectory,
    the friction states and the monitor's bookkeeping are bit-for-bit the same."""
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
        (0.45, 8, 10, step.STATUS_ENERGY),
        (0.45, 12, 3, step.STATUS_INVERTED),
        (0.45, 30, 10**6, step.STATUS_NONFINITE),
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
    dt = factor * stable_time_step(scene, "semi-implicit")
    runs = []
    for threads in (1, 2):
        monitor = BlowupMonitor(scene, s0, "semi-implicit", check_every=check_every)
        st = step.FusedStepper(body, [table], [s0.contacts[0]], None, None, s0.x, s0.v, s0.t, monitor)
        st.threads = threads
        taken = st.advance(3000, dt)
        assert 0 < taken < 3000 and st.failure is not None and st.failure.status == status
        runs.append((taken, st))
    (n1, one), (n2, two) = runs
    assert n1 == n2 and one.failure == two.failure and one.monitor.steps == two.monitor.steps
    assert np.array_equal(one.x, two.x, equal_nan=True)


def _two_threads(pressed):
    scene, s0 = pressed
    st = step.FusedStepper(
        scene.body, [scene.interactions[0]], [s0.contacts[0]], scene.interactions[1], s0.contacts[1], s0.x,
        s0.v, s0.t,
    )  # fmt: skip
    st.threads = 2
    return st, stable_time_step(scene, "semi-implicit")


def _worker_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == "softgrasp-fused-worker"]


def _advance_aside(st, n: int, dt: float) -> BaseException | None:
    """``st.advance(n, dt)`` on a daemon thread (a hang fails the test instead of the run): what it
    raised, or None."""
    raised: list[BaseException | None] = []

    def run() -> None:
        try:
            st.advance(n, dt)
            raised.append(None)
        except BaseException as exc:
            raised.append(exc)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(timeout=120)
    assert not thread.is_alive(), "advance() did not return"
    return raised[0]


def _poll(cond, what: str) -> None:
    for _ in range(20000):
        if cond():
            return
        threading.Event().wait(0.0005)
    raise AssertionError(f"timed out waiting for {what}")


def _held(cond) -> bool:
    """Whether ``cond`` still holds after a pause long enough for a running thread to move on."""
    threading.Event().wait(0.05)
    return cond()


def test_the_worker_waits_for_the_leader_at_each_meeting(pressed):
    """The worker's side of the protocol, the leader played by this test: no node part before the
    step is set up, no body-force part before the leader's node part is done, stop ends it."""
    st, dt = _two_threads(pressed)
    flags = np.zeros(step._S_SIZE, np.int64)
    shared = np.array([dt])
    out = []
    args = (st.x, st.v, st._mass, st._grav, st._body, st._pl, st.pl_active, st.pl_anchor, st._work, False, 0,
            1, flags, shared)  # fmt: skip
    stopped = np.zeros(step._S_SIZE, np.int64)
    stopped[step._S_STOP] = 1
    step._advance_worker(*args[:-2], stopped, shared)  # compiled before the thread starts
    worker = threading.Thread(target=lambda: out.append(step._advance_worker(*args)), daemon=True)
    worker.start()
    try:
        assert _held(lambda: flags[step._S_NODES1] == 0)
        flags[step._S_GO] = 1
        _poll(lambda: flags[step._S_NODES1] == 1, "the worker's node part")
        assert _held(lambda: flags[step._S_BODY1] == 0)  # waits for the leader's node part
        flags[step._S_NODES0] = 1
        _poll(lambda: flags[step._S_BODY1] == 1, "the worker's body forces")
        assert _held(lambda: flags[step._S_NODES1] == 1)  # waits for the next step
    finally:
        flags[step._S_STOP] = 1
        worker.join(timeout=30)
    assert not worker.is_alive() and out == [1]


def test_the_leader_waits_for_the_worker_at_each_meeting(pressed):
    """The leader's side, the worker played by this test: no fingertips, body forces or checks
    before the worker's node part is done, no next step before its body-force part is done (the
    forces at the start taken as given: only the protocol is watched)."""
    st, dt = _two_threads(pressed)
    flags = np.zeros(step._S_SIZE, np.int64)
    shared = np.zeros(1)
    info = st._work[1]
    out = []
    args = (2, dt, False, 0.0, st.t, st.x, st.v, st._mass, st._grav, st._total_mass, st._body, st._pl,
            st.pl_active, st.pl_anchor, st._fg, st._fstate, st._cur, st._work, True, False, st._mon, 0, 1,
            st._gvec, st._fail, flags, shared)  # fmt: skip
    step._advance_leader(*args[:-2], np.zeros(step._S_SIZE, np.int64) + 2**40, np.zeros(1))  # compile
    info[:] = np.nan
    leader = threading.Thread(target=lambda: out.append(step._advance_leader(*args)), daemon=True)
    leader.start()
    try:
        for s in (1, 2):
            _poll(lambda: flags[step._S_NODES0] == s, "the leader's node part")  # noqa: B023
            assert flags[step._S_GO] == s and shared[0] == dt
            assert _held(lambda: np.isnan(info[0, 0]))  # waits for the worker's node part
            flags[step._S_NODES1] = s
            _poll(lambda: not np.isnan(info[0, 0]), "the leader's body forces")
            assert _held(lambda: flags[step._S_GO] == s)  # noqa: B023 - waits for the worker's body forces
            info[0] = np.nan
            flags[step._S_BODY1] = s
        _poll(lambda: flags[step._S_STOP] == 1, "the leader's stop")
    finally:
        flags[step._S_STOP] = 1
        leader.join(timeout=30)
    assert not leader.is_alive() and out[0][:2] == (step.STATUS_OK, 2)


def test_a_failing_worker_thread_stops_the_leader(pressed, monkeypatch):
    """The worker thread failing sets the stop flag: the leader stops waiting for it and the
    failure is raised, instead of a hang."""
    st, dt = _two_threads(pressed)

    def broken(*args):
        raise MemoryError("no memory left")

    monkeypatch.setattr(step, "_advance_worker", broken)
    err = _advance_aside(st, 50, dt)
    assert isinstance(err, RuntimeError) and "second thread failed" in str(err)
    assert isinstance(err.__cause__, MemoryError)
    assert not _worker_threads()
    # the state moved on in part: the stepper refuses to go on from it
    with pytest.raises(RuntimeError, match="failed in an earlier advance"):
        st.advance(1, dt)


def test_a_failing_leader_stops_the_worker(pressed, monkeypatch):
    """The leader failing sets the stop flag too (in Python): the worker thread, waiting for the
    next step, ends."""
    st, dt = _two_threads(pressed)

    def broken(*args):
        threading.Event().wait(0.02)  # the worker is waiting for the first step by now
        raise ValueError("bad input")

    monkeypatch.setattr(step, "_advance_leader", broken)
    err = _advance_aside(st, 50, dt)
    assert isinstance(err, ValueError) and "bad input" in str(err)
    assert not _worker_threads()


def test_auto_threads_fall_back_when_two_threads_slow_down(monkeypatch):
    from softgrasp.linalg import pardiso
    from softgrasp.sim.explicit import FusedThreads

    monkeypatch.setattr(pardiso, "fixed_threads", lambda: None)
    monkeypatch.setattr(pardiso, "choose_threads", lambda: 2)
    th = FusedThreads()
    assert th.choose() == 2 and th.chunk(2, 2000) == 32  # a short first chunk measures the speed
    th.record(2, 32, 32 * 1e-4)
    assert th.chunk(2, 2000) == round(th.chunk_seconds / 1e-4)
    monkeypatch.setattr(pardiso, "choose_threads", lambda: 1)  # our own waiting thread looks busy
    assert th.choose() == 2
    th.record(2, 200, 200 * 1e-2)  # 100x slower per step: another process holds a core
    assert th.choose() == 1 and th.chunk(1, 2000) == 2000
    monkeypatch.setattr(pardiso, "choose_threads", lambda: 2)
    assert th.choose() == 1  # for the rest of the run
    monkeypatch.setattr(pardiso, "choose_threads", lambda: 1)
    assert FusedThreads().choose() == 1
    monkeypatch.setattr(pardiso, "fixed_threads", lambda: 2)
    assert FusedThreads().choose() == 2


def test_step_records_the_hash_of_every_module_it_inlines():
    """The cached kernels of step.py compile in functions of other kernel modules (the block
    kernels' IR, the contact kernels, the elastic helpers, the spin-wait atomics); Numba checks
    only step.py's own source for changes, so step.py records the others' hashes and an edit of
    one of them must renew its entry (and so step.py's cache). Every kernel module step.py takes
    compiled code from has an entry."""
    import hashlib
    import re
    from pathlib import Path

    src = Path(step.__file__)
    imported = set(re.findall(r"^from softgrasp\.kernels\.(\w+) import", src.read_text(), re.M))
    assert {f"{m}.py" for m in imported} == set(step._INLINED_SOURCES_SHA256)
    for name, recorded in step._INLINED_SOURCES_SHA256.items():
        digest = hashlib.sha256((src.parent / name).read_bytes()).hexdigest()
        assert recorded == digest, f"{name} changed: set step._INLINED_SOURCES_SHA256[{name!r}] = {digest!r}"
