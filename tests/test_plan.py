"""The grasp planner (paper Sec. 2, 3.5, 4.3.2): the default plan's physics, its failures, the
implicit holding integrator, and ``softgrasp plan``."""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import re

import numpy as np
import pytest

from softgrasp.cli import main
from softgrasp.errors import ConfigError, InfeasibleGrasp, NotConverged
from softgrasp.grasp.closure import is_force_closure
from softgrasp.grasp.initial import HandLayout, initial_grasp
from softgrasp.grasp.planner import PlanConfig, plan_grasp
from softgrasp.linalg.solve import SolverCache
from softgrasp.model.material import preset
from softgrasp.model.mesh.generate import box, sphere
from softgrasp.model.objects import make_object
from softgrasp.physics.body import build_body
from softgrasp.physics.fingertip.params import ContactParams
from softgrasp.physics.planes import Plane, PlaneContact
from softgrasp.sim.implicit import simulate_implicit
from softgrasp.sim.scene import Scene
from softgrasp.sim.static import solve_static


@pytest.fixture(scope="module")
def sphere_body():
    mesh, material, mass = make_object("sphere")
    return build_body(mesh, material, mass=mass)


@pytest.fixture(scope="module")
def default_plan(sphere_body):
    return plan_grasp(sphere_body, PlanConfig())


# --------------------------------------------------------------------------- initial grasp


def _count_exact_hulls(monkeypatch):
    """Count the exact Ferrari-Canny hulls the ranking computes: (a one-item counter list, the
    uncounted function)."""
    import softgrasp.grasp.initial as initial_mod

    exact = initial_mod.wrench_hull
    calls = [0]

    def counted(*a, **k):
        calls[0] += 1
        return exact(*a, **k)

    monkeypatch.setattr(initial_mod, "wrench_hull", counted)
    return calls, exact


def test_ranked_grasps_follow_the_exact_epsilon_order(sphere_body, monkeypatch):
    """The best-first ranking (cheap bounds refined to exact qualities on demand) gives the same
    grasps in the same order as ranking with no bound at all (every candidate's exact epsilon
    computed, a stable sort), and taking the first grasp computes far fewer exact qualities."""
    import math

    import softgrasp.grasp.initial as initial_mod

    x = np.asarray(sphere_body.mesh.points)
    com = (sphere_body.mass @ x) / sphere_body.total_mass
    facets = sphere_body.mesh.facets
    calls, _ = _count_exact_hulls(monkeypatch)
    pruned = initial_mod.initial_grasps(x, facets, com, 0.8)
    calls[0] = 0
    first = next(initial_mod.ranked_grasps(x, facets, com, 0.8))
    n_first = calls[0]
    monkeypatch.setattr(initial_mod, "ferrari_canny_bounds", lambda P, *a, **k: np.full(len(P), math.inf))
    calls[0] = 0
    full = initial_mod.initial_grasps(x, facets, com, 0.8)
    assert calls[0] >= len(full) > 100
    assert n_first < 0.5 * calls[0]  # the bound prunes
    assert len(pruned) == len(full)
    for a, b in zip(pruned, full, strict=True):
        assert (a.thumb_azimuth, a.spread, a.epsilon) == (b.thumb_azimuth, b.spread, b.epsilon)
    assert (first.thumb_azimuth, first.spread) == (full[0].thumb_azimuth, full[0].spread)


def test_ranked_grasps_leave_out_what_the_caller_skips_and_keep_the_order(sphere_body):
    """A ``skip`` that turns true for a spread angle after the first grasp of that spread came
    (as the planner skips a spread the hand failed on) gives the full ranking without those
    grasps, in the same order."""
    import softgrasp.grasp.initial as initial_mod

    x = np.asarray(sphere_body.mesh.points)
    com = (sphere_body.mass @ x) / sphere_body.total_mass
    full = initial_mod.initial_grasps(x, facets := sphere_body.mesh.facets, com, 0.8)
    failed: set[float] = set()
    taken = []
    for g in initial_mod.ranked_grasps(x, facets, com, 0.8, skip=lambda theta, phi: phi in failed):
        taken.append(g)
        if len(taken) <= 3:
            failed.add(g.spread)
        if len(taken) == 6:
            break
    seen: set[float] = set()
    want = []
    for g in full:
        if g.spread in seen and g.spread in {t.spread for t in taken[:3]}:
            continue
        seen.add(g.spread)
        want.append(g)
    assert len({g.spread for g in taken[:3]}) == 3
    assert [(g.thumb_azimuth, g.spread, g.epsilon) for g in taken] == [
        (g.thumb_azimuth, g.spread, g.epsilon) for g in want[:6]
    ]


def test_ranked_grasps_compute_no_more_exact_qualities_than_a_heap_rebuilt_after_every_bound(
    sphere_body, monkeypatch
):
    """The ranking keeps one heap and replaces an entry whose bound fell when it comes to the top.
    Against the plain best-first search written out here (every candidate's current bound or
    exact quality re-sorted before each step), the first grasps come in the same order after the
    same exact qualities, no more: an entry taken as current after its bound fell would have its
    hull computed early."""
    import softgrasp.grasp.initial as initial_mod
    from softgrasp.grasp.closure import ferrari_canny_bounds, primitive_wrenches_many

    x = np.asarray(sphere_body.mesh.points)
    com = (sphere_body.mass @ x) / sphere_body.total_mass
    captured = []
    best_first = initial_mod._best_first
    monkeypatch.setattr(
        initial_mod, "_best_first", lambda found, *a: captured.append(found) or best_first(found, *a)
    )
    calls, exact_hull = _count_exact_hulls(monkeypatch)
    ranked = initial_mod.ranked_grasps(x, sphere_body.mesh.facets, com, 0.8)
    got = []
    for _ in range(5):  # not one step further: the next grasp would cost more hulls
        g = next(ranked)
        got.append((g.thumb_azimuth, g.spread))
    found = captured[0]

    P = np.array([c[0] for c in found])
    N = -np.array([c[1] for c in found])
    theta = np.array([c[3] for c in found])
    ub = ferrari_canny_bounds(P, N, 0.8, com)
    W = primitive_wrenches_many(P, N, 0.8, com)
    exact = np.full(len(found), np.nan)
    alive = ub > 0.0
    hulls, order = 0, []
    while len(order) < 5:
        value = np.where(np.isnan(exact), ub, exact)
        i = min(np.flatnonzero(alive), key=lambda j: (-round(float(value[j]), 12), j))
        if np.isnan(exact[i]):
            eps, normals = exact_hull(W[i], initial_mod.NEAREST_FACETS)
            hulls += 1
            exact[i] = eps
            rest = alive & np.isnan(exact)
            if eps <= 0.0:
                alive[i] = False
            elif rest.any() and len(normals):
                ub[rest] = np.minimum(
                    ub[rest], initial_mod._support_bound(W[rest], normals, theta[rest] - theta[i])
                )
                alive &= ub > 0.0
            continue
        alive[i] = False
        order.append((found[i][3], found[i][4]))
    assert got == order
    assert calls[0] == hulls > 5


def test_initial_grasp_on_the_sphere_lies_on_a_great_circle_with_the_thumb_opposite(sphere_body):
    """Step 1 on the rubber sphere: three force-closure contacts in the horizontal plane through
    the centre of mass, all at the sphere's radius from it (a great circle), the first and middle
    fingers side by side opposite the thumb (their midpoint within 60 deg of the antipode)."""
    x = np.asarray(sphere_body.mesh.points)
    com = (sphere_body.mass @ x) / sphere_body.total_mass
    ig = initial_grasp(x, sphere_body.mesh.facets, com, 0.8)
    assert np.abs(ig.points[:, 2] - com[2]).max() < 1e-9
    r = np.linalg.norm(ig.points - com, axis=1)
    assert r == pytest.approx(np.full(3, 0.064), rel=0.05)  # on the (faceted) sphere
    assert ig.epsilon > 0 and is_force_closure(ig.points, -ig.normals, 0.8, com)
    thumb = ig.points[0] - com
    mid = 0.5 * (ig.points[1] + ig.points[2]) - com
    cos = thumb @ mid / (np.linalg.norm(thumb) * np.linalg.norm(mid))
    assert cos < math.cos(math.radians(120))
    spread = np.linalg.norm(ig.points[1] - ig.points[2])
    layout = HandLayout()
    assert layout.min_spread <= spread <= layout.max_spread


def test_object_too_large_for_the_hand_is_refused_clearly():
    body = build_body(sphere(0.15, 0.06), preset("rubber"), mass=0.5)
    with pytest.raises(InfeasibleGrasp, match=r"the hand cannot reach this object.*\d+ mm across"):
        plan_grasp(body, PlanConfig())


def test_nearly_frictionless_fingers_fail_with_infeasible_grasp(sphere_body):
    with pytest.raises(InfeasibleGrasp, match=r"mu = 0.01"):
        plan_grasp(sphere_body, PlanConfig(contact=ContactParams(mu=0.01)))


def test_no_hold_before_the_maximum_squeeze_fails_with_the_reason(sphere_body):
    """Low friction and a squeeze limit of 2 % of the reach (~1 mm): the fingers cannot yet hold
    the 50 g sphere there, and the planner says so instead of returning a plan."""
    cfg = PlanConfig(contact=ContactParams(mu=0.2), max_squeeze=0.02, hold_time=0.0)
    with pytest.raises(InfeasibleGrasp, match=r"no hold before the maximum squeeze .* mu = 0.2") as err:
        plan_grasp(sphere_body, cfg)
    # less in all than a rigid sphere needs there: more squeeze, more friction or another object
    found = re.search(r"at least ([\d.]+) N.*reached ([\d.]+) N", str(err.value))
    need, reached = (float(v) for v in found.groups())
    assert reached < need
    assert str(err.value).endswith(
        "allow more squeeze (--max-squeeze, now 0.02), raise the friction coefficient, or grasp a "
        "lighter or stiffer object"
    )


def test_a_closing_that_finds_no_rest_says_where_and_that_another_path_may_pass(sphere_body, monkeypatch):
    """Where no rest is found at a travel, half an increment and a whole one further, before the
    grasp test passes (a stand-in: every travel past 1 mm fails), the plan ends as infeasible at
    that travel, with the solver's diagnosis, what a rigid object would need, and the options
    that make the increments pass other travels (a soft, heavy ball of E = 10.2 kPa found no rest
    at 2.39 mm with 0.5 mm steps and planned with 1 mm ones)."""
    from softgrasp.grasp import closing

    real = closing._advance

    def no_rest_past_1mm(scene, start, t, *args, **kwargs):
        if t > 1e-3:
            raise NotConverged("static solve cycles (forced)")
        return real(scene, start, t, *args, **kwargs)

    monkeypatch.setattr(closing, "_advance", no_rest_past_1mm)
    with pytest.raises(InfeasibleGrasp) as err:
        plan_grasp(sphere_body)
    text = str(err.value)
    assert re.search(r"found no equilibrium of the squeezed object at 1\.\d+ mm of travel", text), text
    assert "static solve cycles (forced)" in text and "--step" in text and "--mesh-size" in text
    assert re.search(r"at least [\d.]+ N of normal force", text), text


def test_no_hold_with_more_than_the_rigid_need_names_the_proportions(sphere_body, monkeypatch):
    """Where the fingers reached more normal force in all than a rigid object needs at their
    contacts (a stand-in for the rigid-body LP's answer), it is their proportions that do not hold:
    the message says so rather than only asking for more friction."""
    from softgrasp.grasp.closing import Closing

    monkeypatch.setattr(
        Closing, "_rigid_need", lambda self: ("; mu = 0.2 needs at least 0.10 N", True)
    )
    cfg = PlanConfig(contact=ContactParams(mu=0.2), max_squeeze=0.02, hold_time=0.0)
    with pytest.raises(InfeasibleGrasp, match="not in the proportions that hold it: allow more squeeze"):
        plan_grasp(sphere_body, cfg)


@pytest.mark.parametrize(
    "kw, needle",
    [
        ({"step": 0.0}, r"plan parameter step must be a number in \[1e-06, 0.01\] m, got 0 m"),
        ({"safety_factor": 0.5}, r"safety_factor must be a number in \[1, 20\], got 0.5"),
        ({"hold_time": 1e300}, r"hold_time must be a number in \(0, 60\] s, got 1e\+300 s"),
        ({"solver": "euler"}, "solver must be one of"),
        ({"step": 0.01}, "must be smaller than the fingertip radius"),
        ({"max_squeeze": 1.5}, r"max_squeeze must be a number in \(0, 1\), got 1.5"),
    ],
)
def test_bad_plan_parameters_raise_config_error(kw, needle):
    with pytest.raises(ConfigError, match=needle):
        PlanConfig(**kw)


# --------------------------------------------------------------------------- the default plan


def test_default_plan_holds_the_sphere_in_equilibrium(default_plan, sphere_body):
    """Eq. 21-22 in the held state (table removed): finger forces and weight sum to < 2 % of the
    weight, torques likewise (relative to weight x radius); the centre of mass moves < 1 mm over
    1 s of holding; the fingers stick (friction margin >= 0)."""
    plan = default_plan
    W = sphere_body.total_mass * 9.81
    total = np.sum([f.force for f in plan.fingers], axis=0) + sphere_body.total_mass * sphere_body.gravity
    assert np.linalg.norm(total) < 0.02 * W
    assert plan.force_residual < 0.02 * W
    assert plan.torque_residual < 0.02 * W * 0.064
    assert plan.hold_time == 1.0 and plan.com_drift < 1e-3
    assert plan.friction_margin >= 0
    # The fingers carry the weight: the vertical components of their forces sum to mg.
    assert total[2] == pytest.approx(0.0, abs=0.02 * W)


def test_default_plan_thumb_carries_the_largest_force_and_forces_are_minimal(default_plan):
    """As on the paper's Table 2, the thumb balancing two fingers pushes hardest. The held normal
    forces are what a rigid analysis at those contacts requires, within a factor 3: they would
    hold a rigid object (utilisation <= 1), a third of them would not (utilisation > 1/3), and
    their sum is at least the smallest sum that can hold it."""
    plan = default_plan
    norms = [f.force_norm for f in plan.fingers]
    assert norms[0] == max(norms)
    normal = np.array([f.normal_force for f in plan.fingers])
    assert np.isfinite(plan.rigid_normal_forces).all()
    assert 1.0 / 3.0 < plan.rigid_utilisation <= 1.0
    assert normal.sum() >= plan.rigid_normal_forces.sum() * (1 - 1e-9)
    assert (normal <= 3.0 * plan.rigid_normal_forces).all(), (normal, plan.rigid_normal_forces)
    # The closing approached in whole steps to just before the first touch, then squeezed in
    # increments that double the travel past the touch (from 1 % of the fingertip radius, at most
    # a step) until the grasp test passed, then solved within the last increment for the least
    # passing travel: the plan's squeeze is that of the first passing travel there.
    order = np.argsort(plan.travel, kind="stable")
    touch = plan.first_contact_travel.min()
    path = [t for t in plan.travel[order] if t <= touch - 1e-7 + 1e-12]
    assert np.allclose(np.diff([0.0, *path])[:-1], 0.0005) and path[-1] == pytest.approx(touch - 1e-7)
    held_travel = plan.fingers[0].penetration + plan.first_contact_travel[0]
    assert plan.feasible.sum() >= 1 and held_travel == pytest.approx(plan.travel[plan.feasible].min())
    squeeze = [t for t in plan.travel if t > touch]
    assert squeeze[0] == pytest.approx(touch - 1e-7 + 0.00008, abs=1e-12)
    assert 3 <= len(squeeze) <= 10


def test_default_plan_history_is_monotone_and_penetration_from_first_contact(default_plan):
    """Force grows with travel; the plan is held at the passing increment of least travel; the
    set-point penetration is the held travel minus each finger's first-contact travel."""
    plan = default_plan
    assert (np.diff(plan.travel) > 0).all()
    assert (np.diff(plan.force_norm, axis=0) >= -1e-9).all()  # squeezing harder each increment
    assert (plan.penetration >= 0).all()
    held_travel = plan.fingers[0].penetration + plan.first_contact_travel[0]
    assert held_travel == pytest.approx(plan.travel[plan.feasible].min(), abs=1e-12)
    pen = held_travel - plan.first_contact_travel
    assert [f.penetration for f in plan.fingers] == pytest.approx(np.maximum(pen, 0.0))


@pytest.mark.slow
def test_quasistatic_and_dynamic_closing_agree(sphere_body, default_plan):
    """The paper's explicit Runge-Kutta through each increment (fingers at 50 mm/s) and the
    quasi-static Newton solve give each finger's final force within 10 %."""
    dyn = plan_grasp(sphere_body, PlanConfig(solver="dynamic"))
    assert dyn.increments == default_plan.increments
    for a, b in zip(dyn.fingers, default_plan.fingers, strict=True):
        assert a.force_norm == pytest.approx(b.force_norm, rel=0.10)


def test_the_plan_reports_every_newton_system_it_solved(sphere_body, default_plan, monkeypatch):
    """``GraspPlan.solver_stats`` counts the Newton systems of the plan's closing (the settle, the
    closing, the hold check; the critical scale's force-controlled checks apart, as
    ``margin_systems``), as a wrapper around the static solver's linear solve counts them; the
    default plan's repeat solves the same number."""
    from softgrasp.grasp import planner
    from softgrasp.sim import newton

    calls = []
    real = newton.solve_newton_system
    counting = [True]

    margin_calls = []

    def counted(*args, **kw):
        (calls if counting[0] else margin_calls).append(1)
        return real(*args, **kw)

    in_margin = []

    def uncounted_margin(*args, **kw):
        counting[0] = False
        before = len(calls)
        try:
            return real_margin(*args, **kw)
        finally:
            counting[0] = True
            in_margin.append(len(calls) - before)

    real_margin = planner.critical_scale
    monkeypatch.setattr(planner, "critical_scale", uncounted_margin)

    from softgrasp.grasp import closing
    from softgrasp.grasp.settle import settle_on_table
    from softgrasp.linalg import pardiso

    in_hold_checks, in_increments = [], []
    real_check, real_advance = closing.check_hold, closing._advance

    def check_counted(*args, **kw):
        before = len(calls)
        out = real_check(*args, **kw)
        in_hold_checks.append(len(calls) - before)
        return out

    def advance_counted(*args, **kw):
        before = len(calls)
        out = real_advance(*args, **kw)
        in_increments.append(len(calls) - before)
        return out

    monkeypatch.setattr(newton, "solve_newton_system", counted)
    monkeypatch.setattr(closing, "check_hold", check_counted)
    monkeypatch.setattr(closing, "_advance", advance_counted)
    plan = plan_grasp(sphere_body, PlanConfig())
    assert plan.solver_stats["systems"] == len(calls) > 0
    assert plan.solver_stats["systems"] == default_plan.solver_stats["systems"]
    # By phase: the closing and the hold checks as counted inside them, the settle as counted for
    # a settle alone.
    phases = [plan.solver_stats[k] for k in ("settle_systems", "closing_systems", "hold_check_systems")]
    assert sum(phases) == plan.solver_stats["systems"] and min(phases) > 0
    assert plan.solver_stats["hold_check_systems"] == sum(in_hold_checks) > 0
    assert plan.solver_stats["closing_systems"] == sum(in_increments) > 0
    # the critical scale's checks, counted apart
    assert in_margin == [0] and plan.solver_stats["margin_systems"] == len(margin_calls) > 0
    calls.clear()
    with pardiso.blas_one_thread():
        settle_on_table(sphere_body, PlanConfig(), SolverCache())
    assert plan.solver_stats["settle_systems"] == len(calls)


def test_load_steps_to_their_looser_tolerance_keep_the_set_points(sphere_body, default_plan, monkeypatch):
    """The closing increments, the force-controlled increments of the critical scale's checks and
    the release steps but the last stop at ``STEP_RTOL`` (1e-4 of the largest force); the last
    release step, where the hold starts, and the held state at ``HELD_RTOL`` (1e-9). Against a
    plan whose steps are all solved to 1e-9: the same set-points to 1e-4 of themselves (a
    hundredth of the 1 % force tolerance; measured 1.5e-5: the friction history the looser
    increments leave differs in its last digits), the same closing path (travel to 1e-5, grasp
    tests, hold checks) with its per-step forces to 1e-4 of the largest, the same critical-scale
    checks and verdicts, fewer Newton systems in the closing, the hold check and the critical
    scale, the same in the settle."""
    from softgrasp.grasp import closing, config, force_control, hold

    assert config.STEP_RTOL == 1e-4 and config.HELD_RTOL == 1e-9
    release_rtols: list[float] = []
    real_solve = hold.solve_static

    def recorded(scene, state, **kw):
        if "support" in [i.name for i in scene.interactions]:
            release_rtols.append(kw["rtol"])
        return real_solve(scene, state, **kw)

    from softgrasp.grasp import planner

    def closing_only(body, cfg, normal, **kw):  # the critical scale's own hold checks not recorded
        n = len(release_rtols)
        out = real_margin(body, cfg, normal, **kw)
        del release_rtols[n:]
        return out

    real_margin = planner.critical_scale
    monkeypatch.setattr(planner, "critical_scale", closing_only)
    monkeypatch.setattr(hold, "solve_static", recorded)
    again = plan_grasp(sphere_body, PlanConfig())
    assert release_rtols == [1e-4] * (config.RELEASE_STEPS - 1) + [1e-9]
    assert again.solver_stats == default_plan.solver_stats
    monkeypatch.setattr(closing, "STEP_RTOL", 1e-9)  # the closing increments
    monkeypatch.setattr(hold, "STEP_RTOL", 1e-9)  # the release steps
    monkeypatch.setattr(force_control, "STEP_RTOL", 1e-9)  # the critical scale's closings
    tight = plan_grasp(sphere_body, PlanConfig())
    for a, b in zip(default_plan.fingers, tight.fingers, strict=True):
        np.testing.assert_allclose(a.force, b.force, rtol=0, atol=1e-4 * b.force_norm)
    # The solved travel moves with the grasp test's values, by far less than the force tolerance
    # (measured 4e-6 of itself).
    np.testing.assert_allclose(default_plan.travel, tight.travel, rtol=1e-5)
    np.testing.assert_array_equal(default_plan.feasible, tight.feasible)
    assert [w for _, w in default_plan.hold_checks] == [w for _, w in tight.hold_checks]
    np.testing.assert_allclose(
        [t for t, _ in default_plan.hold_checks], [t for t, _ in tight.hold_checks], rtol=1e-5
    )
    # per-step forces to 1e-4 of the closing's largest, the increments' own tolerance's measure
    scale = float(tight.force_norm.max())
    np.testing.assert_allclose(default_plan.force_norm, tight.force_norm, rtol=0, atol=1e-4 * scale)
    stats, tight_stats = default_plan.solver_stats, tight.solver_stats
    assert stats["closing_systems"] < tight_stats["closing_systems"]
    assert stats["hold_check_systems"] < tight_stats["hold_check_systems"]
    assert stats["settle_systems"] == tight_stats["settle_systems"]
    assert stats["margin_systems"] < tight_stats["margin_systems"]
    assert [h for _, h in default_plan.margin.checks] == [h for _, h in tight.margin.checks]
    np.testing.assert_allclose(
        [s for s, _ in default_plan.margin.checks], [s for s, _ in tight.margin.checks], rtol=1e-5
    )


# --------------------------------------------------------------------------- implicit holding


def test_implicit_euler_free_fall_matches_the_closed_form():
    """Backward Euler under constant gravity: v_n = v0 + n g dt exactly and
    x_n = x0 + n dt v0 + g dt^2 n (n + 1) / 2 (a rigid translation: no internal force)."""
    body = build_body(box(0.02, 2), preset("foam"), mass=0.01)
    scene = Scene(body, ())
    v0 = np.array([0.1, 0.0, 0.5])
    state = scene.initial_state()
    state = state.replace(v=np.tile(v0, (body.n_nodes, 1)))
    dt, n = 0.01, 20
    end = simulate_implicit(scene, state, n * dt, dt)
    g = body.gravity
    assert end.t == pytest.approx(n * dt)
    assert end.v == pytest.approx(np.tile(v0 + n * dt * g, (body.n_nodes, 1)), abs=1e-9)
    shift = n * dt * v0 + g * dt**2 * n * (n + 1) / 2
    assert end.x - np.asarray(body.mesh.points) == pytest.approx(np.tile(shift, (body.n_nodes, 1)), abs=1e-9)


# --------------------------------------------------------------------------- command line


def test_plan_cli_with_a_config_file_writes_everything(tmp_path):
    """``softgrasp plan --config``: the TOML keys are used, and plan.json (schema softgrasp.plan/2),
    history.csv and the three figures are written."""
    cfg = tmp_path / "plan.toml"
    cfg.write_text('mu = 0.8\nhold_time = 0.2\nstep = 0.0005\nsolver = "quasistatic"\n')
    out = tmp_path / "out"
    assert main(["plan", "--config", str(cfg), "--out", str(out)]) == 0
    doc = json.loads((out / "plan.json").read_text())
    assert doc["schema"] == "softgrasp.plan/2"
    assert doc["object"]["name"] == "sphere" and doc["object"]["mass_kg"] == pytest.approx(0.05)
    assert set(doc["object"]["material"]) >= {"E_Pa", "nu"}
    assert doc["parameters"]["hold_time_s"] == 0.2 and doc["parameters"]["contact"]["mu"] == 0.8
    assert [f["name"] for f in doc["fingers"]] == ["thumb", "first", "middle"]
    for f in doc["fingers"]:
        assert f["force_norm_N"] == pytest.approx(np.linalg.norm(f["force_N"]))
        assert len(f["initial_contact_m"]) == 3 and len(f["final_position_m"]) == 3
    assert set(doc["equilibrium"]) >= {
        "satisfied",
        "force_residual_N",
        "torque_residual_Nm",
        "friction_margin",
    }
    assert doc["equilibrium"]["satisfied"] is True
    assert doc["hold"]["duration_s"] == 0.2
    checks = doc["hold"]["checks"]
    assert checks and checks[-1]["result"] == "held"
    assert all(c["travel_m"] > 0 for c in checks)
    rows = list(csv.DictReader((out / "history.csv").open()))
    assert len(rows) == 3 * doc["increments"]
    assert [r["finger"] for r in rows[:3]] == ["thumb", "first", "middle"]
    for name in ("forces.png", "force_penetration.png", "grasp.png"):
        assert (out / name).stat().st_size > 10_000


@pytest.mark.parametrize(
    "content, needle",
    [
        ("mu = 0.8\nsqueeze = 2\n", "unknown key(s) squeeze"),
        ("mu = 'high'\n", "mu must be a number in [0, 5], got 'high'"),
        ("mu = [\n", "is not valid TOML"),
    ],
)
def test_plan_cli_bad_config_is_one_clear_line(tmp_path, capsys, content, needle):
    cfg = tmp_path / "bad.toml"
    cfg.write_text(content)
    out = tmp_path / "out"
    assert main(["plan", "--config", str(cfg), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("softgrasp: error:") and needle in err[0]
    assert not out.exists()


@pytest.mark.slow
def test_default_plan_job_runs(tmp_path, capsys):
    """The README's main job, ``softgrasp plan`` with every default, prints the Table 2 layout."""
    out = tmp_path / "default"
    assert main(["plan", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "thumb" in printed and "penetration mm" in printed
    assert json.loads((out / "plan.json").read_text())["equilibrium"]["satisfied"] is True


def test_plan_cli_zero_values_are_used_not_replaced_by_defaults(tmp_path, capsys):
    """``--mu 0`` means frictionless fingertips (no force closure: one clear error line after the
    phases' lines, exit status 1: valid input, no grasp), not the default 0.8."""
    out = tmp_path / "out"
    assert main(["plan", "--mu", "0", "--out", str(out)]) == 1
    *phases, err = capsys.readouterr().err.strip().splitlines()
    assert all(line.startswith("softgrasp: plan: ") for line in phases), phases
    assert err.startswith("softgrasp: error: ") and "mu = 0" in err and "force closure" in err
    assert not out.exists()


def test_implicit_integration_checks_its_step_and_accepts_an_empty_span():
    body = build_body(box(0.02, 1), preset("foam"), mass=0.01)
    scene = Scene(body, ())
    state = scene.initial_state()
    assert simulate_implicit(scene, state, state.t, 0.01) is state
    for dt in (0.0, -0.05, float("nan")):
        with pytest.raises(ConfigError, match="implicit time step"):
            simulate_implicit(scene, state, 0.1, dt)


def test_on_its_stable_facet_a_sphere_started_lowered_settles_where_started_level():
    """On its most stable hull facet, the 2 998-node sphere started lowered by half its estimated
    approach (five nodes touching from the first iterate where the facet's three touch level)
    comes to the rest found from the level start, both on the multigrid path the planner lowers
    on and balanced to 1e-9 of the largest force: the same positions to 1e-6 of the largest
    displacement (1.0e-7 measured: the rolling mode is nearly neutral), the table carrying the
    weight, in fewer Newton systems (5 against 8 measured)."""
    from softgrasp.grasp.config import HELD_RTOL
    from softgrasp.grasp.settle import lowered_start, stable_pose, table_under
    from softgrasp.linalg import pardiso

    mesh, material, mass = make_object("sphere", 0.007)
    body = build_body(mesh, material, mass=mass)
    x = stable_pose(body, np.asarray(mesh.points))
    table = table_under(x, PlanConfig().table_mu)
    scene = Scene(body, (table,))
    guess = lowered_start(body, x)
    zmin = x[:, 2].min()
    assert (guess[:, 2] < zmin).sum() > (x[:, 2] <= zmin + 1e-12).sum() == 3  # more than the facet presses in
    rests, systems = [], []
    for start in (None, guess):
        cache = SolverCache(method="amg")  # the path the planner starts lowered on
        with pardiso.blas_one_thread():
            rests.append(
                solve_static(scene, scene.initial_state(x), rtol=HELD_RTOL, cache=cache, guess=start)[0]
            )
        systems.append(cache.stats["systems"])
    level, lowered = rests
    scale = float(np.abs(level.x - x).max())
    np.testing.assert_allclose(lowered.x, level.x, rtol=0, atol=1e-6 * scale)
    f = table.static_forces(body, lowered.x, 0.0, lowered.contacts[0])
    assert f[:, 2].sum() == pytest.approx(body.total_mass * float(np.linalg.norm(body.gravity)), rel=1e-5)
    assert systems[1] < systems[0]


def test_a_flat_face_down_is_not_lowered():
    """The foam cube stands on its whole bottom face: lowering it would press in no node that does
    not touch already (the predicted patch is the face), so the settle starts level on every
    path."""
    from softgrasp.grasp.settle import lowered_start

    mesh, material, mass = make_object("cube")
    body = build_body(mesh, material, mass=mass)
    assert lowered_start(body, np.asarray(mesh.points)) is None
    sphere_mesh, material, mass = make_object("sphere", 0.007)
    sphere_body = build_body(sphere_mesh, material, mass=mass)
    assert lowered_start(sphere_body, np.asarray(sphere_mesh.points)) is not None


@pytest.mark.parametrize("method", ["auto", "amg"])
def test_the_settle_starts_lowered_where_its_systems_go_to_multigrid(monkeypatch, method):
    """On the multigrid path the settle starts lowered (:func:`softgrasp.grasp.settle.lowered_start`),
    as meshed where the mesh stands (the default sphere) and on the most stable facet where it
    balances on a node; where PARDISO or a sparse LU solves (the default path at these sizes) it
    starts level."""
    from softgrasp.grasp import settle

    starts = []
    real = settle.solve_static

    def recorded(scene, state, **kw):
        starts.append((kw.get("guess"), kw.get("max_iter")))
        return real(scene, state, **kw)

    monkeypatch.setattr(settle, "solve_static", recorded)
    monkeypatch.setattr(settle, "LOWERED_MIN_NODES", 0)  # these small bodies stand for large ones
    # Rubber balls whose predicted patches reach beyond the nodes touching as placed: the 2 465-node
    # default sphere (50 g), and a 150 mm ball of 5 kg meshed pole-down.
    for mesh, mass, stands in (
        (make_object("sphere", 0.0075)[0], 0.05, True),
        (sphere(0.15, 0.06), 5.0, False),
    ):
        body = build_body(mesh, preset("rubber"), mass=mass)
        starts.clear()
        _, _, placed = settle.settle_on_table(body, PlanConfig(), SolverCache(method=method))
        assert np.array_equal(placed, mesh.points) == stands
        guess, max_iter = starts[0]
        if method == "amg":  # pressed into the table under the placement, for a limited number of iterations
            assert guess[:, 2].min() < placed[:, 2].min() and max_iter == settle.LOWERED_MAX_ITER
            # Settled lowered, or (the 2 465-node sphere: no rest within the limit) level after it.
            assert len(starts) == 1 or [start is None for start, _ in starts[1:]] == [True]
        else:
            assert len(starts) == 1 and guess is None and max_iter is None  # solve_static's own limit
    # Below LOWERED_MIN_NODES the settle starts level on multigrid too.
    monkeypatch.setattr(settle, "LOWERED_MIN_NODES", 10**9)
    starts.clear()
    settle.settle_on_table(body, PlanConfig(), SolverCache(method=method))
    assert [start is None for start, _ in starts] == [True]


def test_a_lowered_start_that_finds_no_rest_is_followed_by_the_level_one(monkeypatch):
    """A lowered start that does not converge is followed by the level start from the same
    placement, which settles; where every start fails, and so do backward Euler steps from each
    placement, the error names each start and its failure."""
    from softgrasp.grasp import settle

    body = build_body(sphere(0.15, 0.06), preset("rubber"), mass=5.0)  # balanced on one node
    real = settle.solve_static
    starts = []

    def lowered_fails(scene, state, **kw):
        starts.append(kw.get("guess") is not None)
        if kw.get("guess") is not None:
            raise NotConverged("static solve did not converge (forced)")
        return real(scene, state, **kw)

    monkeypatch.setattr(settle, "solve_static", lowered_fails)
    monkeypatch.setattr(settle, "LOWERED_MIN_NODES", 0)  # a small body standing for a large one
    cache = SolverCache(method="amg")
    dropped = []
    real_changed = cache.scene_changed
    cache.scene_changed = lambda: (dropped.append(len(starts)), real_changed())
    state, table, placed = settle.settle_on_table(body, PlanConfig(), cache)
    assert starts == [True, False]
    assert dropped == [1]  # the solver's state dropped after the failed start, before the next
    f = table.static_forces(body, state.x, 0.0, state.contacts[0])
    assert f[:, 2].sum() == pytest.approx(body.total_mass * float(np.linalg.norm(body.gravity)), rel=1e-5)

    def always_fails(scene, state, **kw):
        raise NotConverged("static solve did not converge (forced)")

    monkeypatch.setattr(settle, "solve_static", always_fails)
    monkeypatch.setattr(settle, "proximal_solve", lambda scene, state, t, **kw: always_fails(scene, state))
    for mesh, tried in (
        (sphere(0.15, 0.06), ["on its most stable facet, lowered", "on its most stable facet",
                              "on its most stable facet, by backward Euler steps"]),
        (make_object("sphere")[0], ["as meshed, lowered", "as meshed", "as meshed, by backward Euler steps",
                                    "on its most stable facet, lowered", "on its most stable facet",
                                    "on its most stable facet, by backward Euler steps"]),
    ):  # fmt: skip
        with pytest.raises(NotConverged, match="no rest on the table") as info:
            settle.settle_on_table(
                build_body(mesh, preset("rubber"), mass=5.0), PlanConfig(), SolverCache(method="amg")
            )
        message = info.value.diagnosis
        assert [part.split(": ")[0] for part in message.split(": ", 1)[1].split("; ")] == tried
        # the advice: how far the weight strains it, and what may help
        advice = re.fullmatch(
            r"its weight strains it by about ([\d.]+) % \(rho g H / E\).*--mesh-size.*", info.value.advice
        )
        D = float(np.ptp(mesh.points[:, 2]))  # a ball: rho = 5 kg / (pi D^3 / 6), H = D
        expected = 100 * 5.0 / (math.pi * D**3 / 6) * 9.81 * D / preset("rubber").E
        assert float(advice.group(1)) == pytest.approx(expected, rel=0.1)


@pytest.mark.slow
def test_the_fine_sphere_settles_on_the_table_without_being_kicked_along_its_rolling_mode(caplog):
    """The 18 233-node sphere (3.6 mm elements) comes to rest on the table, its first friction
    pass (the table's stick, before the Coulomb limits are taken) within a dozen Newton iterations,
    a rest that carries its weight with its centre of mass above the nodes it stands on. Its
    rolling mode is nearly neutral: balanced to 1.2e-6 at the 9th iteration on an indefinite
    matrix, the step followed along the negative curvature (4x, then 16x) kicked it off and it
    wandered for 47 iterations or found no rest in 60 (the default plan failed). The later passes,
    where the patch's edge nodes slip at their Coulomb limits and free that mode a little, took 35
    iterations more."""
    import logging

    from scipy.spatial import ConvexHull

    from softgrasp.grasp.settle import settle_on_table
    from softgrasp.linalg import pardiso

    if not pardiso.available():
        pytest.skip("the failure was on PARDISO's path (MKL not installed)")
    mesh, material, mass = make_object("sphere", 0.0036)
    body = build_body(mesh, material, mass=mass)
    cache = SolverCache(method="pardiso")  # where it failed (beyond PARDISO_MAX_DOF by default now)
    with pardiso.blas_one_thread(), caplog.at_level(logging.DEBUG, logger="softgrasp.sim.static"):
        state, table, _ = settle_on_table(body, PlanConfig(), cache)
    first = [int(m.group(1)) for m in re.finditer(r"friction pass 1: (\d+) Newton its", caplog.text)]
    assert first and first[0] <= 12, first
    f = table.static_forces(body, state.x, 0.0, state.contacts[0])
    weight = body.total_mass * float(np.linalg.norm(body.gravity))
    assert f[:, 2].sum() == pytest.approx(weight, rel=1e-5)
    on = np.flatnonzero(f[:, 2] > 0)
    com = body.mass @ state.x / body.total_mass
    hull = ConvexHull(state.x[on, :2])
    assert (hull.equations[:, :2] @ com[:2] + hull.equations[:, 2] < 0).all()


def test_an_object_that_stands_is_set_down_where_it_stands_before_it_is_turned(monkeypatch):
    """Where Newton finds no rest for the mesh as it stands (as on a ball meshed finely at its
    bottom, whose iterates wander along its nearly neutral rolling mode), backward Euler steps
    set it down there before the settle turns it onto its most stable facet (on the refined ball
    that facet lay 40 degrees round): it rests as placed, the table carrying its weight, where
    Newton's rest lies (the default sphere's, whose Newton does find it)."""
    from softgrasp.grasp import settle

    body = build_body(*make_object("sphere")[:2], mass=0.05)
    real = settle.solve_static
    calls = []

    def as_meshed_fails(scene, state, **kw):
        calls.append(np.array_equal(state.x, body.mesh.points))
        if len(calls) == 1:  # the first start, as meshed
            raise NotConverged("static solve cycles (forced)")
        return real(scene, state, **kw)

    newton, _, _ = settle.settle_on_table(body, PlanConfig(), SolverCache())
    monkeypatch.setattr(settle, "solve_static", as_meshed_fails)
    state, table, placed = settle.settle_on_table(body, PlanConfig(), SolverCache())
    assert calls[0] and np.array_equal(placed, body.mesh.points)  # not turned
    f = table.static_forces(body, state.x, 0.0, state.contacts[0])
    weight = body.total_mass * float(np.linalg.norm(body.gravity))
    assert f[:, 2].sum() == pytest.approx(weight, rel=1e-5)
    assert np.linalg.norm(state.x - newton.x, axis=1).max() < 1e-5  # 0.9 um measured


def test_a_plan_is_the_same_whichever_way_the_mesh_is_given():
    """The physics does not change under a rigid motion of the object. The 2 998-node sphere does
    not stand as meshed and the settle turns it onto a stable facet; the same tets given already
    placed that way (a body built afresh from those points) stand as given. Both plans hold the
    sphere at the same set-points (2e-4 apart measured): the contact law measures the mesh where
    the fingertips land on the rest shape as it lies on the table, not as it was given (that
    moves the first finger's set-point by 2.7 %)."""
    from softgrasp.model.mesh.tetmesh import TetMesh

    mesh, material, mass = make_object("sphere", 0.007)
    given = plan_grasp(build_body(mesh, material, mass=mass))
    assert not np.array_equal(given.placed, mesh.points)  # turned by the settle
    placed = build_body(TetMesh(given.placed, mesh.tets), material, mass=mass)
    again = plan_grasp(placed)
    assert np.array_equal(again.placed, given.placed)  # stands as given
    np.testing.assert_allclose(again.setpoints, given.setpoints, rtol=2e-3)


def test_a_mesh_balanced_on_one_node_is_stood_on_a_stable_facet():
    """A coarse sphere meshed pole-down balances on one node, an unstable pose that tips over. The
    planner's settling turns it onto the hull facet whose plane is nearest the centre of mass: there
    the centre of mass projects inside the facet and three nodes carry the object."""
    from scipy.spatial import ConvexHull

    from softgrasp.grasp.settle import stable_pose

    body = build_body(sphere(0.15, 0.06), preset("rubber"), mass=0.5)
    x = stable_pose(body, np.asarray(body.mesh.points))
    low = np.flatnonzero(x[:, 2] < x[:, 2].min() + 1e-9)
    assert len(low) >= 3  # a facet down, not a node
    com = body.mass @ x / body.total_mass
    tri = x[low[:3], :2]
    # Barycentric coordinates of the centre of mass's projection in the bottom facet: all positive.
    T = np.column_stack([tri[1] - tri[0], tri[2] - tri[0]])
    l1, l2 = np.linalg.solve(T, com[:2] - tri[0])
    assert min(l1, l2, 1 - l1 - l2) > 0
    assert ConvexHull(x).volume == pytest.approx(ConvexHull(body.mesh.points).volume, rel=1e-12)
    table = PlaneContact(Plane(np.array([0.0, 0.0, x[:, 2].min()]), np.array([0.0, 0.0, 1.0])), mu=0.5)
    rest = Scene(body, (table,))
    state, _ = solve_static(rest, rest.initial_state(x), cache=SolverCache())
    # At rest it stands on the nodes the table pushes (those below its plane), with the centre of
    # mass above their support polygon: a stable rest, not a node balanced under it.
    xs = state.x
    support = xs[xs[:, 2] < x[:, 2].min(), :2]
    assert len(support) >= 3
    hull = ConvexHull(support)
    c = body.mass @ xs / body.total_mass
    assert (hull.equations[:, :2] @ c[:2] + hull.equations[:, 2] < 0).all()


def test_default_plan_is_reachable_by_the_hand(default_plan):
    """The hand model places each fingertip at its start centre, moves it along its straight
    closing line to its final centre (the last row of its joint path) within the joint limits, and
    keeps its palm and joints outside the object (only fingertips touch it)."""
    from scipy.spatial import ConvexHull

    from softgrasp.hand.placement import transform

    plan = default_plan
    hand, pl = plan.config.hand, plan.placement
    assert hand is not None and pl is not None and plan.joint_paths is not None
    hull = ConvexHull(plan.placed).equations
    for j, f in enumerate(("thumb", "first", "middle")):
        path = plan.joint_paths[f]
        lo, hi = hand.limits(f)
        assert (path >= lo - 1e-12).all() and (path <= hi + 1e-12).all()
        tips = transform(pl.palm_pose, np.array([hand.forward(f, q) for q in path]))
        np.testing.assert_allclose(tips[0], plan.start_centres[j], atol=1e-5)
        np.testing.assert_allclose(tips[-1], plan.centres[j], atol=5e-4)
        line = plan.centres[j] - plan.start_centres[j]
        off = np.cross(tips - plan.start_centres[j], line / np.linalg.norm(line))
        assert np.linalg.norm(off, axis=1).max() < 5e-4  # on the straight closing line
        joints = transform(pl.palm_pose, hand.link_points(f, path[-1]))
        joints = joints[np.linalg.norm(joints - joints[-1], axis=1) > hand.fingertip_radius(f)]
        assert ((joints @ hull[:, :3].T + hull[:, 3]).max(axis=1) > 0).all()
    assert (pl.palm_pose[:3, 3] @ hull[:, :3].T + hull[:, 3]).max() > 0


def test_plan_without_a_hand_model_uses_the_layout_alone(sphere_body):
    plan = plan_grasp(sphere_body, PlanConfig(hand=None, hold_time=0.0))
    assert plan.placement is None and plan.joint_paths is None
    assert plan.initial.epsilon > 0


def test_a_fingertip_radius_other_than_the_hands_is_refused():
    with pytest.raises(
        ConfigError, match=r"fingertip radius 6 mm differs from the hand's thumb fingertip \(8 mm"
    ):
        PlanConfig(fingertip_radius=0.006)
    assert PlanConfig(fingertip_radius=0.006, hand=None).fingertip_radius == 0.006


def test_plan_hand_option_names_a_missing_urdf(tmp_path, capsys):
    assert main(["plan", "--hand", str(tmp_path / "nohand.urdf"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "nohand.urdf does not exist" in err and "Traceback" not in err
    assert not (tmp_path / "o" / "plan.json").exists()


def test_hold_checks_record_why_the_fingers_closed_further(default_plan):
    """Every hold verification is recorded with its outcome. The default plan holds at its first
    check. The 5 kPa rubber sphere, at the grasp test's least passing squeeze, is not held as the
    table goes; the fingers squeeze further until it is, then split the bracket: every check not
    held says why and lies below the held travel, which is the least travel held and the plan's,
    with more force in the held state than the grasp test alone asked for."""
    assert len(default_plan.hold_checks) == 1 and default_plan.hold_checks[0][1] == "held"
    mesh, material, mass = make_object("sphere")
    soft = build_body(mesh, dataclasses.replace(material, E=5e3), mass=mass)
    plan = plan_grasp(soft, PlanConfig())
    checks = plan.hold_checks
    assert checks[0][1] != "held" and len(checks) >= 2
    held = [t for t, why in checks if why == "held"]
    failed = [(t, why) for t, why in checks if why != "held"]
    assert held and plan.fingers[0].penetration + plan.first_contact_travel[0] == pytest.approx(min(held))
    for t, why in failed:
        assert t < min(held)
        assert why.startswith(("the object slides out of the fingers", "the ")), why
    assert plan.travel[plan.feasible].min() == pytest.approx(checks[0][0])


def test_set_points_do_not_depend_on_round_off():
    """The default plan twice, the second on the mesh with every coordinate changed by about
    1e-13 of itself (the size of round-off in a sum taken in another order): the same set-points
    to 1e-6. (With the fingertips starting exactly one step from tangency, whether a facet counted
    as touching at the first step's end was round-off's choice, and the set-points took one of
    several values 1-4 % apart.)"""
    from softgrasp.model.mesh.tetmesh import TetMesh

    mesh, mat, mass = make_object("sphere")
    jitter = 1e-13 * np.random.default_rng(12).standard_normal(mesh.points.shape)
    moved = TetMesh(np.asarray(mesh.points) * (1.0 + jitter), np.asarray(mesh.tets), name="sphere")
    forces = []
    for m in (mesh, moved):
        plan = plan_grasp(build_body(m, mat, mass=mass), PlanConfig())
        forces.append([f.force_norm for f in plan.fingers])
    np.testing.assert_allclose(forces[1], forces[0], rtol=1e-6)
