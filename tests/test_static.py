"""Static solver: analytic self-weight, resting on the table, agreement with dynamics, errors."""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np
import pytest

from softgrasp.errors import NotConverged
from softgrasp.linalg.solve import SolverCache
from softgrasp.model.material import Material, preset
from softgrasp.model.mesh import box
from softgrasp.model.objects import make_object
from softgrasp.physics.body import build_body
from softgrasp.physics.fingertip.contact import FingertipContact
from softgrasp.physics.fingertip.params import ContactParams, Fingertip
from softgrasp.physics.forces import assemble_blocks
from softgrasp.physics.planes import ELASTIC_SLIP, Plane, PlaneContact
from softgrasp.physics.supports import Tether
from softgrasp.sim import newton
from softgrasp.sim.explicit import settle
from softgrasp.sim.implicit import Inertia
from softgrasp.sim.newton import cycle_period
from softgrasp.sim.newton_matrix import newton_matrix
from softgrasp.sim.scene import Scene
from softgrasp.sim.static import extrapolated, solve_increment, solve_static

G = 9.80665


def _table(mu: float = 0.5) -> PlaneContact:
    return PlaneContact(Plane([0, 0, 0], [0, 0, 1]), mu=mu, name="table")


@pytest.mark.parametrize("nu", [0.25, 0.45])
def test_column_shortens_under_its_own_weight_as_a_bar(nu):
    """On a frictionless table a prism carries uniaxial stress rho g (H - z): it shortens by
    rho g H^2 / (2 E), whatever nu."""
    H, E, rho = 0.06, 1e5, 1000.0
    mesh = box((0.03, 0.03, H), (4, 4, 8))
    body = build_body(mesh, Material(E, nu, rho))
    scene = Scene(body, (_table(0.0), Tether("xy")))
    state, _ = solve_static(scene, scene.initial_state())
    X = np.asarray(mesh.points)
    u = state.x[:, 2] - X[:, 2]
    sag = u[X[:, 2] > H - 1e-9].mean() - u[X[:, 2] < 1e-9].mean()
    assert sag == pytest.approx(-rho * G * H**2 / (2 * E), rel=0.04)


@pytest.mark.parametrize("normal", [(0.0, 0.0, 1.0), (0.3, -0.2, 0.9)])
def test_the_table_at_rest_holds_by_coulombs_law_with_an_elastic_slip(normal):
    """A box pressed into a (level or tilted) table, its anchors displaced, at the start of a
    Newton pass (its limits taken there): the table's static forces are zero on every node that
    does not touch; on a touching node the friction is at most mu times the normal force, equal
    to it against the stretch where the node has moved more than its elastic slip (0.5 % of its
    edges' length) and in proportion below. Within the pass the forces are minus the
    central-difference gradient of the table's energy, and the diagonal blocks their derivative;
    outside a pass the same law is taken at the penetrations at hand."""
    from softgrasp.physics.planes import ELASTIC_SLIP

    body = build_body(box(0.04, 3), preset("foam"), mass=0.01)
    n = np.asarray(normal) / np.linalg.norm(normal)
    P = np.eye(3) - np.outer(n, n)
    rng = np.random.default_rng(2)
    x = np.asarray(body.mesh.points) + 2e-4 * rng.standard_normal((body.n_nodes, 3))
    mu = 0.7
    table = PlaneContact(Plane(np.array([0.0, 0.0, 0.0]) + 0.004 * n, n), mu=mu, name="table")
    state = table.init_state(body, x)
    # Half the anchors within the elastic slip (about 70 um here), half beyond it.
    shift = rng.standard_normal(state.anchor.shape)
    length = np.where(np.arange(body.n_nodes) % 2 == 0, 3e-5, 3e-4)
    shift *= (length / np.linalg.norm(shift, axis=1))[:, None]
    state = replace(state, anchor=state.anchor + shift)
    outside = table.static_forces(body, x, 0.0, state)
    state = table.static_begin(body, x, 0.0, state)
    f = table.static_forces(body, x, 0.0, state)
    np.testing.assert_array_equal(f, outside)
    pen = -(x - table.plane.point) @ n
    touching = np.flatnonzero(pen > 0)
    assert 0 < len(touching) < body.n_nodes
    assert not f[pen <= 0].any()
    fn, ft = f[touching] @ n, f[touching] @ P
    np.testing.assert_allclose(fn, table.stiffness(body)[touching] * pen[touching], rtol=1e-12)
    s = (x - (table.plane.point + state.anchor))[touching] @ P
    r = np.linalg.norm(s, axis=1)
    edges = [body.rest_length[(body.edges == i).any(axis=1)] for i in touching]
    elastic = ELASTIC_SLIP * np.array([np.mean(e) for e in edges])  # of each node's edges' mean length
    slips = r > elastic
    assert 0 < slips.sum() < len(touching)
    np.testing.assert_allclose(np.linalg.norm(ft[slips], axis=1), mu * fn[slips], rtol=1e-12)
    assert (np.einsum("ij,ij->i", ft[slips], s[slips]) < 0).all()  # against the stretch
    stick = -(mu * fn / elastic)[:, None] * s
    np.testing.assert_allclose(ft[~slips], stick[~slips], rtol=1e-9, atol=1e-15)
    h = 1e-8
    grad = np.zeros_like(x)
    for i in range(body.n_nodes):
        for a in range(3):
            e = np.zeros_like(x)
            e[i, a] = h
            up, down = table.energy(body, x + e, 0.0, state), table.energy(body, x - e, 0.0, state)
            grad[i, a] = (up - down) / (2 * h)
    assert np.abs(f + grad).max() <= 1e-6 * np.abs(f).max()
    on, blocks = table.jacobian_diagonal(body, x, 0.0, state)
    assert set(on.tolist()) == set(np.flatnonzero(pen >= 0).tolist())
    for i, B in zip(on, blocks, strict=True):
        df = np.zeros((3, 3))
        for a in range(3):
            e = np.zeros_like(x)
            e[i, a] = h
            up = table.static_forces(body, x + e, 0.0, state)[i]
            df[:, a] = (up - table.static_forces(body, x - e, 0.0, state)[i]) / (2 * h)
        np.testing.assert_allclose(B, df, rtol=1e-6, atol=1e-6 * np.abs(B).max())


def test_the_table_keeps_its_stick_stiffness_through_a_solve_and_its_forces_when_it_ends():
    """Within a static solve the table's stick springs keep the stiffness of the first pass's rest
    (``PlaneState.stick``): the first pass's update freezes each touching node's limit over its
    elastic slip there, and a later update, where the penetrations differ, keeps it. With it a
    node sticks by K s up to its limit (its elastic slip then c / K) and slips at its limit beyond,
    the forces minus the energy's gradient. When the solve ends the anchors move so that the law
    outside a solve (its limit over its elastic slip) gives every node the same force at the
    rest: the forces before and after are equal."""
    body = build_body(box(0.04, 3), preset("foam"), mass=0.01)
    rng = np.random.default_rng(5)
    x = np.asarray(body.mesh.points) + 2e-4 * rng.standard_normal((body.n_nodes, 3))
    table = PlaneContact(Plane(np.array([0.0, 0.0, 0.004]), np.array([0.0, 0.0, 1.0])), mu=0.6, name="table")
    state = table.static_begin(body, x, 0.0, table.init_state(body, x))
    shift = rng.standard_normal(state.anchor.shape) * np.array([1.0, 1.0, 0.0])
    shift *= (np.where(np.arange(body.n_nodes) % 2 == 0, 2e-5, 4e-4) / np.linalg.norm(shift, axis=1))[:, None]
    state = replace(state, anchor=state.anchor + shift)
    first = table.static_update(body, x, 0.0, state)
    pen = 0.004 - x[:, 2]
    on = pen > 0
    frozen = first.stick
    np.testing.assert_allclose(
        frozen[on], first.cap[on] / (ELASTIC_SLIP * body.node_edge_length[on]), rtol=1e-12
    )
    assert np.isnan(frozen[~on]).all()
    deeper = x - np.array([0.0, 0.0, 5e-5])  # every penetration 50 um deeper: the limits grow
    later = table.static_update(body, deeper, 0.0, replace(first, anchor=state.anchor))
    np.testing.assert_array_equal(later.stick, frozen)
    assert (later.cap[on] > first.cap[on]).all()
    f = table.static_forces(body, deeper, 0.0, later)
    s = deeper[on] - (table.plane.point + later.anchor[on])
    s[:, 2] = 0.0
    r = np.linalg.norm(s, axis=1)
    cap, K = later.cap[on], frozen[on]
    slips = K * r > cap
    assert 0 < slips.sum() < on.sum()
    ft = f[on][:, :2]
    np.testing.assert_allclose(ft[~slips], -(K[:, None] * s)[~slips][:, :2], rtol=1e-12, atol=1e-18)
    np.testing.assert_allclose(np.linalg.norm(ft[slips], axis=1), cap[slips], rtol=1e-12)
    h = 1e-8
    for i in np.flatnonzero(on)[:6]:
        for a in range(2):
            e = np.zeros_like(x)
            e[i, a] = h
            grad = (
                table.energy(body, deeper + e, 0.0, later) - table.energy(body, deeper - e, 0.0, later)
            ) / (2 * h)
            assert abs(f[i, a] + grad) <= 1e-6 * np.abs(f).max()
    ended = table.static_finish(body, deeper, 0.0, later)
    assert ended.cap is None and ended.stick is None
    np.testing.assert_allclose(
        table.static_forces(body, deeper, 0.0, ended), f, rtol=0, atol=1e-12 * np.abs(f).max()
    )


def test_a_block_on_the_table_stays_below_coulombs_limit_and_finds_no_rest_above_it():
    """A block on a level table pushed sideways by a dead load spread over its nodes, ramped in
    ten load steps: at 0.9 of mu times its weight the table balances the push (friction = -push,
    the block creeping by about its elastic slip); ramped to 1.1 times it, no rest is found once
    the push nears mu W (it slides)."""
    from softgrasp.sim.loads import RampedLoad

    mu = 0.5
    body = build_body(box(0.03, 3), Material(2e5, 0.3, 1000.0))
    W = body.total_mass * G
    x0 = np.asarray(body.mesh.points)
    for ratio, rests in ((0.9, True), (1.1, False)):
        push = np.zeros((body.n_nodes, 3))
        push[:, 0] = ratio * mu * W * body.mass / body.total_mass
        scene = Scene(body, (_table(mu), RampedLoad(push, x0, start=0.0, end=1.0)))
        state, _ = solve_static(scene, scene.initial_state(), t=0.0)
        try:
            for t in np.linspace(0.1, 1.0, 10):
                state, _ = solve_static(scene, state, t=float(t))
        except NotConverged:
            assert not rests, f"no rest found at {t:g} of {ratio} mu W"
            assert t > 1.0 / ratio - 0.1  # it slides once the push passes mu W
            continue
        assert rests, f"the block rests at {ratio} mu W"
        R = scene.interactions[0].static_forces(body, state.x, 1.0, state.contacts[0]).sum(axis=0)
        assert R[0] == pytest.approx(-ratio * mu * W, rel=1e-6)
        assert R[2] == pytest.approx(W, rel=1e-6)
        assert np.abs(state.x[:, 0] - x0[:, 0]).max() < 2e-4  # its elastic slip: 0.5 % of 10 mm edges


def test_sphere_rests_on_table_without_rolling():
    mesh, mat, mass = make_object("sphere", 0.016)
    body = build_body(mesh, mat, mass=mass)
    table = _table()
    scene = Scene(body, (table,))
    state, _ = solve_static(scene, scene.initial_state())
    R = table.static_forces(body, state.x, 0.0, state.contacts[0]).sum(axis=0)
    assert R[2] == pytest.approx(body.total_mass * G, rel=1e-8)
    assert np.abs(R[:2]).max() < 1e-9 * R[2]
    com0 = body.mass @ np.asarray(mesh.points) / body.total_mass
    com = body.mass @ state.x / body.total_mass
    assert np.hypot(*(com - com0)[:2]) < 1e-3  # leans on its tripod, does not roll away


@pytest.mark.parametrize("method", ["auto", "amg"])
def test_newton_matrices_share_the_body_pattern_and_leave_it_intact(method):
    """The Newton matrices are the body's Jacobian pattern with fresh values: they share its
    index arrays (int32, as SciPy keeps them; no per-matrix copy), and a whole static solve on
    either linear solver (PARDISO's upper triangle, multigrid's node blocks and hierarchy) leaves
    those arrays as they were."""
    mesh, mat, mass = make_object("sphere", 0.016)
    body = build_body(mesh, mat, mass=mass)
    pattern = body._jacobian_pattern
    assert pattern.indices.dtype == np.int32 and pattern.indptr.dtype == np.int32
    before = (pattern.indices.copy(), pattern.indptr.copy())
    J = body.internal_jacobian(np.asarray(mesh.points))
    assert np.shares_memory(J.indices, pattern.indices) and np.shares_memory(J.indptr, pattern.indptr)
    scene = Scene(body, (_table(),))
    solve_static(scene, scene.initial_state(), cache=SolverCache(method=method))
    assert np.array_equal(pattern.indices, before[0]) and np.array_equal(pattern.indptr, before[1])


def test_a_predicted_start_finds_the_same_rest_in_fewer_iterations():
    """A block on a rough table pressed down by a rigid plate in two equal load steps: the second
    step started from the first two rests extrapolated (the response is nearly linear) finds the
    rest found from the first step's alone, to the solver's tolerance (10 rtol once the table's
    friction passes agree), in fewer Newton iterations; a guess that would invert tets is
    ignored."""
    mesh = box((0.03, 0.03, 0.02), (3, 3, 2))
    body = build_body(mesh, Material(1e5, 0.3, 1000.0))
    plate = PlaneContact(Plane([0, 0, 0.02], [0, 0, -1], velocity=[0, 0, -1e-3]), mu=0.5, name="plate")
    scene = Scene(body, (_table(), plate))
    start = scene.initial_state()
    one, _ = solve_static(scene, start, t=1.0)
    plain, info_plain = solve_static(scene, one, t=2.0)
    predicted, info_predicted = solve_static(scene, one, t=2.0, guess=extrapolated(one.x, start.x))
    scale = float(np.ptp(plain.x - np.asarray(mesh.points)))
    np.testing.assert_allclose(predicted.x, plain.x, rtol=0, atol=10 * 1e-9 * scale)
    assert info_predicted.newton_iterations < info_plain.newton_iterations
    inverted = one.x.copy()
    inverted[:, 2] *= -1.0  # every tet turned inside out
    same, info_same = solve_static(scene, one, t=2.0, guess=inverted)
    np.testing.assert_array_equal(same.x, plain.x)
    assert info_same.newton_iterations == info_plain.newton_iterations


def test_an_increment_solved_to_a_looser_tolerance_stops_there_near_the_tight_rest():
    """``solve_increment`` passes ``rtol`` to the static solve (the planner's closing increments
    use ``STEP_RTOL`` = 1e-4 of the largest force, its held state 1e-9): a block pressed 3 mm by
    a rigid plate, solved to 1e-6, stops balanced to that (within the 10 rtol the static solve
    accepts once the table's friction passes agree) and not to 1e-9, in fewer Newton iterations,
    at a rest within 10 rtol of the displacement of the one solved to 1e-9."""
    mesh = box((0.03, 0.03, 0.02), (3, 3, 2))
    body = build_body(mesh, Material(1e5, 0.3, 1000.0))
    plate = PlaneContact(Plane([0, 0, 0.02], [0, 0, -1], velocity=[0, 0, -3e-3]), mu=0.5, name="plate")
    scene = Scene(body, (_table(), plate))
    start = scene.initial_state()

    def balance(state):  # the largest unbalanced force over the largest force present
        f, f_int = scene.static_forces(state.x, 1.0, state.contacts), body.internal_forces(state.x)
        return np.abs(f).max() / max(np.abs(f_int).max(), np.abs(f - f_int).max())

    loose, it_loose, _ = solve_increment(scene, start, 1.0, rtol=1e-6)
    tight, it_tight, _ = solve_increment(scene, start, 1.0, rtol=1e-9)
    assert 1e-8 < balance(loose) <= 10 * 1e-6  # solve_static accepts 10 rtol after the slip return
    assert balance(tight) <= 10 * 1e-9
    assert it_loose < it_tight
    moved = float(np.ptp(tight.x - np.asarray(mesh.points)))
    assert np.abs(loose.x - tight.x).max() <= 10 * 1e-6 * moved


def test_a_tipping_ball_follows_negative_curvature_to_the_same_rest(monkeypatch):
    """The ball meshed at 7.5 mm stands on three nodes and tips onto more of them: on the way
    Newton's matrix is indefinite and its shifted steps creep (the tipping grows by ~15 % per
    iteration). Following each such step while the potential falls reaches the rest the creeping
    steps reach, to a nanometre, in fewer Newton iterations (double-precision factors: with
    single-precision ones the rounding noise moves both counts by several iterations from run to
    run, 25-32 followed against 32-45 crept)."""
    mesh, mat, mass = make_object("sphere", 0.0075)
    body = build_body(mesh, mat, mass=mass)
    scene = Scene(body, (_table(),))
    followed, info = solve_static(scene, scene.initial_state(), cache=SolverCache(precision="double"))
    monkeypatch.setattr(newton, "NEGATIVE_CURVATURE_MAX_GROWTH", 1.0)  # the shifted steps only
    crept, info_crept = solve_static(scene, scene.initial_state(), cache=SolverCache(precision="double"))
    np.testing.assert_allclose(followed.x, crept.x, rtol=0, atol=1e-9)
    assert info.newton_iterations < info_crept.newton_iterations


def test_newton_progress_is_logged_one_record_per_iteration(caplog):
    """At DEBUG level the solver reports every Newton iteration and every friction pass: as many
    records of each as StaticInfo counts."""
    mesh, mat, mass = make_object("sphere", 0.016)
    body = build_body(mesh, mat, mass=mass)
    scene = Scene(body, (_table(),))
    with caplog.at_level(logging.DEBUG, logger="softgrasp.sim"):
        _, info = solve_static(scene, scene.initial_state())
    its = [r.getMessage() for r in caplog.records if r.getMessage().startswith("newton it")]
    passes = [r.getMessage() for r in caplog.records if r.getMessage().startswith("friction pass")]
    assert len(its) == info.newton_iterations > 0
    assert len(passes) == info.friction_passes
    assert passes[-1].startswith(f"friction pass {info.friction_passes}: ")


def test_cycling_newton_iterates_are_recognised():
    """Newton's iterates that return to the same unbalanced forces with a period of 2-4, twice in
    a row, cycle (and would to the iteration limit); converging or merely noisy ones do not."""
    assert cycle_period([5.0, 1e-3, 2e-3, 1e-3, 2e-3]) == 2
    assert cycle_period([9.4e-3, 9.36e-3, 3.2e-2, 9.4e-3, 9.36e-3, 3.2e-2]) == 3
    assert cycle_period([1.0, 0.5, 1.0, 0.5, 0.25]) == 0  # converging after one return
    assert cycle_period([1e-3, 2e-3, 1e-3]) == 0  # one return only
    assert cycle_period([1e-3 * 0.5**k for k in range(12)]) == 0
    assert (
        cycle_period([4.196770e-02, 5.245263e-02, 4.196556e-02, 5.248980e-02, 4.196556e-02, 5.248980e-02])
        == 2
    )
    # Drifting: not a cycle.
    assert cycle_period([1e-3, 2e-3, 1e-3 * (1 + 1e-4), 2e-3, 1e-3 * (1 + 2e-4)]) == 0


def test_a_newton_crawl_that_cannot_balance_in_time_is_recognised():
    """A solve whose unbalanced force falls by 1.5 % per iteration (an object sliding out of fingers
    that cannot hold it) would need hundreds of iterations: given up on, at that rate. One
    converging linearly fast enough to reach the target in the iterations left, speeding up on its
    way to quadratic convergence, quadratically, or through a step that raised the unbalanced
    force (another merit accepted it) is not."""
    crawl = [6e-4 * 0.985**k for k in range(6)]
    assert newton._crawl_rate(crawl, left=14, target=1.6e-7) == pytest.approx(0.985)
    assert not newton._crawl_rate(crawl[:4], left=14, target=1.6e-7)  # too few iterations to judge
    assert not newton._crawl_rate(crawl, left=1000, target=1.6e-7)  # would get there in time
    assert not newton._crawl_rate(crawl, left=14, target=1e-3)  # balanced already
    halving = [6e-4 * 0.5**k for k in range(6)]
    assert not newton._crawl_rate(halving, left=14, target=1.6e-7)
    assert not newton._crawl_rate([1.0, 0.9, 0.78, 0.64, 0.48], left=55, target=1e-6)  # speeding up
    assert not newton._crawl_rate([1e-1, 1e-2, 1e-4, 1e-8, 1e-12, 1e-15], left=14, target=1e-16)
    assert not newton._crawl_rate([*crawl[:3], 7e-4, *crawl[3:]], left=14, target=1.6e-7)


def test_a_newton_climb_away_from_balance_is_recognised():
    """A solve whose unbalanced force rose at each of its last ``CLIMB_ITERATIONS`` iterations after
    full Newton steps on positive definite matrices (an object sliding out of fingers that cannot
    hold it: the release step of a hold check that fails) is given up on. One that rose for fewer
    in a row and then fell (contacts engaging over several iterates, as a foam cube's closing
    increment converged after 7 rises), or rose on shifted steps (a body tipping over on an
    indefinite matrix), is not."""
    k = newton.CLIMB_ITERATIONS
    assert k > 7  # above the longest rise of a solve that converged
    sliding = [3.08e-3 * 1.1**i for i in range(k + 1)]
    assert newton.climbs(sliding, [True] * k)
    assert newton.climbs([1.0, 1e-3, *sliding], [False, True, *[True] * k])  # after a fall
    assert not newton.climbs(sliding[:-1], [True] * (k - 1))  # one rise too few
    assert not newton.climbs(sliding, [True] * (k - 1) + [False])  # the last rise on a shifted step
    engaging = [4.32e-3, 3.51e-2, 7.57e-2, 0.137, 0.198, 0.199, 0.275, 0.385, 1e-6]
    assert not newton.climbs(engaging, [True] * (len(engaging) - 1))
    flat = [*sliding[:5], sliding[4], *sliding[5:]]
    assert not newton.climbs(flat, [True] * (len(flat) - 1))  # a repeat is not a rise


def test_a_newton_solve_that_finds_no_lower_unbalanced_force_for_its_patience_stalls():
    """A release step whose object slides out of the fingers (the 2 196-node sphere's below its
    critical scale: the unbalanced force rising from 3.0e-3 N, each full step followed by a
    short one that lowers it a little) stalls once ``patience`` iterations in a row stay above the
    lowest before them; one that converges with a setback (a step the energy merit accepted, the
    unbalanced force up for a few iterations) does not, nor one with too few iterations to judge."""
    rising = [3.0e-3]
    for _ in range(20):
        rising += [rising[-1] * 1.08, rising[-1] * 1.075]
    assert newton.stalls(rising[:13], 12)
    assert not newton.stalls(rising[:12], 12)  # too few to judge
    setback = [2e-1, 1.5e-2, 2e-4, 3e-4, 5e-4, 4e-4, 1e-4, 1e-6]
    assert not any(newton.stalls(setback[:n], 4) for n in range(1, len(setback) + 1))
    assert newton.stalls([*setback[:3], 3e-4, 5e-4, 4e-4, 2e-4], 4)  # back to, not below, its low
    converging = [1e-1 * 0.3**k for k in range(12)]
    assert not any(newton.stalls(converging[:n], 1) for n in range(1, 13))


def test_a_release_step_starts_again_only_after_a_failure_a_nearer_start_can_mend(monkeypatch):
    """With a patience (a release step), a failure from the guess that advises smaller steps (a
    crawl, a cycle: a start nearer the rest can mend it) is solved again from the state's
    positions, and one that does not (iterates climbing, stalling: the body not held there) is
    final; without a patience, every failure from a guess starts again."""
    from softgrasp.sim import static

    body = build_body(box(0.04, 2), Material(2e4, 0.3, 200.0))
    scene = Scene(body, ())
    state = scene.initial_state()
    rest = object()
    for patience, advice, again in (
        (12, None, False),
        (12, newton.SMALLER_STEPS, True),
        (None, None, True),
        (None, newton.SMALLER_STEPS, True),
    ):
        starts = []

        def attempt(*args, advice=advice, starts=starts):
            guess = args[-2]
            starts.append(guess is not None)
            if guess is not None:
                raise NotConverged("static solve from the guess failed", advice)
            return rest

        monkeypatch.setattr(static, "_solve_static", attempt)
        if again:
            assert solve_static(scene, state, guess=state.x + 1e-4, patience=patience) is rest
            assert starts == [True, False]
        else:
            with pytest.raises(NotConverged, match="from the guess failed"):
                solve_static(scene, state, guess=state.x + 1e-4, patience=patience)
            assert starts == [True]


def test_static_and_dynamic_rest_states_agree():
    """The static solve and a damped dynamic settle find the same rest state on the table.

    The table is frictionless (friction makes the rest state depend on the path: nodes that slip
    while the body bounces stick elsewhere) and weak tethers hold the sliding modes, so the
    equilibrium is unique."""
    body = build_body(box(0.04, 3), Material(2e4, 0.3, 200.0), damping_ratio=0.5)
    scene = Scene(body, (_table(0.0), Tether("xy")))
    static, _ = solve_static(scene, scene.initial_state())
    dynamic = settle(scene, scene.initial_state(), t_max=2.0, tol_velocity=1e-5)
    sag_static = static.x[:, 2].max() - 0.04
    sag_dynamic = dynamic.x[:, 2].max() - 0.04
    assert sag_static < 0
    assert sag_dynamic == pytest.approx(sag_static, rel=0.02)
    assert np.abs(dynamic.x - static.x).max() < 0.01 * abs(sag_static)


def test_unsupported_body_is_reported():
    body = build_body(box(0.04, 2), Material(2e4, 0.3, 200.0))
    scene = Scene(body, ())
    with pytest.raises(NotConverged, match="not held"):
        solve_static(scene, scene.initial_state())


def test_non_cubic_cells_warn_about_anisotropy():
    with pytest.warns(UserWarning, match="cannot be made isotropic"):
        build_body(box((0.03, 0.03, 0.05), (3, 3, 6)), Material(1e5, 0.3, 100.0))


def test_constraints_and_tethers_hold_a_frictionless_squeeze_alike():
    """Two independent ways of removing the rigid motions frictionless plates leave free (exact
    linear constraints with multipliers, weak tether springs) give the same equilibrium, and both
    carry no net reaction under the symmetric load."""
    from softgrasp.sim.static import rigid_constraints

    body = build_body(box(0.04, 3), Material(5e4, 0.4, 100.0))
    X = np.asarray(body.mesh.points)
    bottom = PlaneContact(Plane([0, 0, 0], [0, 0, 1]), mu=0.0, name="bottom")
    top = PlaneContact(Plane([0, 0, 0.04], [0, 0, -1], velocity=[0, 0, -1.0]), mu=0.0, name="top")
    C = rigid_constraints(X, body.mass, "xyZ")
    s1 = Scene(body, (bottom, top))
    a, info = solve_static(s1, s1.initial_state(), t=0.001, constraints=C)
    tether = Tether("xy")
    s2 = Scene(body, (bottom, top, tether))
    b, _ = solve_static(s2, s2.initial_state(), t=0.001)
    f1 = top.static_forces(body, a.x, a.t, a.contacts[1]).sum(axis=0)[2]
    f2 = top.static_forces(body, b.x, b.t, b.contacts[1]).sum(axis=0)[2]
    # The tethers resist the lateral (Poisson) expansion with 1e-6 of each node's stiffness: a bias
    # of the order of that ratio (times the ~6 springs per node), nothing more.
    bias = 20 * tether.ratio
    assert f1 < 0 and f2 == pytest.approx(f1, rel=bias)
    assert np.abs(a.x - b.x).max() < bias * np.abs(a.x - X).max()
    assert np.abs(info.constraint_forces_N).max() < 1e-9 * abs(f1)
    assert np.abs(tether.total_force(body, b.x)).max() < 1e-9 * abs(f1)


def test_a_balanced_iterate_is_accepted_when_shifted_steps_stall(monkeypatch):
    """The 27 749-node sphere's settle on the table: its rolling stiffness (~1e-10 of the largest,
    of either sign) made the multigrid solves shift the diagonal (Levenberg-Marquardt), and the
    shifted steps crept along the rolling mode, ~1 % per iteration, from a state already balanced
    to 1e-6 of the largest force, until the limit. Reproduced on a small scene with a free mode (a
    box on a frictionless table slides freely): from a state balanced to ~1e-7, with a linear
    solver that must shift, gains 1 % per step and drifts 1 um along the free mode, Newton accepts
    the balanced state at once (it ran to the iteration limit before); with solves that converge
    it is not accepted early."""
    mesh = box((0.03, 0.03, 0.03), (3, 3, 3))
    body = build_body(mesh, Material(1e5, 0.3, 1000.0))
    scene = Scene(body, (_table(0.0),))
    rest, _ = solve_static(scene, scene.initial_state(), rtol=1e-12)
    f_int = np.abs(body.internal_forces(rest.x)).max()
    # The solver's scale (the largest force present) and a displacement that leaves ~1e-7 of it
    # unbalanced: balanced to STALL_RTOL, far from the 1e-12 asked for.
    f_ext = scene.static_forces(rest.x, 0.0, rest.contacts) - body.internal_forces(rest.x)
    scale = max(f_int, np.abs(f_ext).max())
    d = np.random.default_rng(0).standard_normal(rest.x.shape)
    r1 = np.abs(scene.static_forces(rest.x + 1e-9 * d, 0.0, rest.contacts)).max()
    start = replace(rest, x=rest.x + 1e-9 * (1e-7 * scale / r1) * d)
    f0 = np.abs(scene.static_forces(start.x, 0.0, start.contacts)).max()
    assert 1e-8 * scale < f0 < newton.STALL_RTOL * scale
    real = newton.solve_newton_system

    def crawling(A, b, C, x, cache, **kw):
        dx, lam = real(A, b, C, x, cache, **kw)
        cache.stats["shifted"] = cache.stats.get("shifted", 0) + 1  # an indefinite matrix, shifted
        drift = np.zeros_like(dx)
        drift[0::3] = 1e-6  # a slide along the table: the free mode
        return 0.01 * dx + drift, lam  # the shifted step: 1 % of the way, and drifting

    monkeypatch.setattr(newton, "solve_newton_system", crawling)
    _, info = solve_static(scene, start, rtol=1e-12, max_iter=60)
    assert info.newton_iterations <= 2
    assert info.residual_N <= newton.STALL_RTOL * scale
    monkeypatch.setattr(newton, "solve_newton_system", real)  # converging solves: no early stop
    _, info = solve_static(scene, start, rtol=1e-12, max_iter=60)
    assert info.residual_N < 1e-3 * f0


# ------------------------------------------------------------------ the Newton matrix's assembly


@dataclass(frozen=True)
class _Strut:
    """A linear spring between two nodes that no edge joins (a rigid link of a fixture): its
    Jacobian couples nodes outside the body's pattern."""

    i: int
    j: int
    k: float
    name: str = "strut"

    def init_state(self, body, x, t=0.0):
        return None

    def static_forces(self, body, x, t, state):
        f = np.zeros_like(x)
        d = self.k * (x[self.j] - x[self.i] - (body.mesh.points[self.j] - body.mesh.points[self.i]))
        f[self.i] += d
        f[self.j] -= d
        return f

    def energy(self, body, x, t, state):
        d = x[self.j] - x[self.i] - (body.mesh.points[self.j] - body.mesh.points[self.i])
        return 0.5 * self.k * float(d @ d)

    def jacobian(self, body, x, t, state):
        k = -self.k * np.eye(3)
        rows, cols = np.array([self.i, self.i, self.j, self.j]), np.array([self.i, self.j, self.i, self.j])
        return assemble_blocks(body.n_nodes, rows, cols, np.array([k, -k, -k, k]))

    def update(self, body, x, v, t, state):
        return None

    def static_update(self, body, x, t, state):
        return None


def _sparse_sum(scene, x, t, contacts):
    """-(body + interactions) summed as sparse matrices, the approximate (non-symmetric)
    interactions' entries outside the body's pattern left out."""
    body = scene.body
    J = body.internal_jacobian(x)
    inside = J.copy()
    inside.data[:] = 1.0
    for inter, st in zip(scene.interactions, contacts, strict=True):
        Ji = inter.jacobian(body, x, t, st)
        if not getattr(inter, "symmetric_jacobian", True):
            Ji = Ji.multiply(inside)
        J = J + Ji
    return -J.toarray()


def test_newton_matrix_summed_into_the_body_pattern_is_the_sparse_sum_entry_for_entry():
    """The Newton matrix is assembled in place in the body's fixed pattern (the table's and the
    inertia's diagonal blocks and the fingertip's blocks added at their positions). With a rough
    fingertip pressed into a cube on a rough table, during a backward Euler step, and with a strut
    joining two far corners (outside the pattern), it is the sparse matrices' sum, bit for bit."""
    body = build_body(box(0.05, 4), preset("foam"), mass=0.0125)
    tip = Fingertip(0.008, centre=[0.003, 0.002, 0.0565], velocity=[0.3, 0.0, -1.0])
    fc = FingertipContact((tip,), ContactParams(mu=0.8))
    X = np.asarray(body.mesh.points)
    far = int(np.argmax(np.linalg.norm(X - X[0], axis=1)))
    scene = Scene(body, (_table(1.0), fc, Inertia(X + 1e-4, 1e-3), _Strut(0, far, 50.0)))
    pressed = Scene(body, (_table(1.0), fc))
    state, _ = solve_static(pressed, pressed.initial_state(), t=0.5e-3)
    x = state.x + 1e-5 * np.sin(np.arange(X.size)).reshape(-1, 3)
    contacts = (state.contacts[0], state.contacts[1], None, None)
    A, exact = newton_matrix(scene, x, 0.5e-3, contacts, 0.05)
    assert len(fc.pairs(body, x, 0.5e-3)) > 0 and exact is not None
    assert np.array_equal(A.toarray(), _sparse_sum(scene, x, 0.5e-3, contacts))
    assert A[3 * far, 0] == -50.0  # the strut's coupling is there: A = -J


def test_a_static_solve_called_alone_holds_numpys_blas_to_one_thread(monkeypatch):
    """A static solve called outside a plan holds NumPy's BLAS to one thread while it runs, as the
    planner does for a whole plan (OpenBLAS's threads otherwise compete with the solver's), and
    finds the same rest as a solve inside the planner's hold."""
    import contextlib

    from softgrasp.linalg import pardiso

    body = build_body(box(0.02, 3), preset("foam"), mass=0.01)
    table = PlaneContact(Plane(np.zeros(3), np.array([0.0, 0.0, 1.0])), mu=0.5)
    scene = Scene(body, (table,))
    depth = [0]
    held_when_forces: list[bool] = []
    real = pardiso.blas_one_thread
    real_forces = Scene.static_forces

    @contextlib.contextmanager
    def spy():
        depth[0] += 1
        try:
            with real():
                yield
        finally:
            depth[0] -= 1

    def forces(self, *args, **kwargs):
        held_when_forces.append(depth[0] > 0)
        return real_forces(self, *args, **kwargs)

    monkeypatch.setattr(pardiso, "blas_one_thread", spy)
    monkeypatch.setattr(Scene, "static_forces", forces)
    alone, _ = solve_static(scene, scene.initial_state(), cache=SolverCache())
    # Held for the whole solve, the force evaluations between the linear solves too (not only
    # inside PARDISO's solves, which hold it themselves).
    assert held_when_forces and all(held_when_forces)
    monkeypatch.setattr(Scene, "static_forces", real_forces)
    with real():
        held, _ = solve_static(scene, scene.initial_state(), cache=SolverCache())
    np.testing.assert_allclose(alone.x, held.x, rtol=0, atol=1e-12)
