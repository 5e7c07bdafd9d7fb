"""Robust set-points (``softgrasp plan --uncertain``) and the force-controlled closing that checks
set-points: the closing reaches its set-points and agrees with the position-controlled plan, the
robust set-points hold the object for every sampled parameter set (checked again here, outside the
cluster), the nominal plan's set-points do not, and friction is found to drive the force."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from softgrasp.cli import main
from softgrasp.errors import ConfigError, InfeasibleGrasp, NotConverged
from softgrasp.grasp.force_control import hold_setpoints
from softgrasp.grasp.planner import plan_grasp
from softgrasp.io.atomic import write_json
from softgrasp.io.options import PLAN_DEFAULTS, contact_params, load_body, plan_config
from softgrasp.io.plan_document import plan_document
from softgrasp.io.planfile import load_plan_grasp
from softgrasp.sweep.robust import (
    _unholdable,
    nominal_values,
    parse_uncertain,
    robust_setpoints,
    sample_requirements,
)

NOMINAL = {"mu": 0.8, "E": 80e3, "nu": 0.45, "density": 1000.0, "mass": 0.05, "a2": 0.0, "a3": 0.0}


@pytest.fixture(scope="module")
def sphere():
    return load_body("sphere")


@pytest.fixture(scope="module")
def nominal_plan(sphere):
    return plan_grasp(sphere, plan_config(PLAN_DEFAULTS, contact_params(None, 0.8)))


@pytest.mark.parametrize(
    "text, low, high",
    [
        ("mu=0.4..0.8", 0.4, 0.8),
        ("E=±20%", 64e3, 96e3),
        ("E=+-25%", 60e3, 100e3),
        ("mu = ±0.1", 0.7, 0.9),
        ("density=900..1.1e3", 900.0, 1100.0),
        ("a2=-1..1", -1.0, 1.0),
    ],
)
def test_uncertain_ranges(text, low, high):
    u = parse_uncertain(text, NOMINAL)
    assert u.low == pytest.approx(low) and u.high == pytest.approx(high)


@pytest.mark.parametrize(
    "text, message",
    [
        ("mu", "give NAME=LOW..HIGH"),
        ("radius=1..2", "not an uncertain parameter"),
        ("mu=0.8..0.4", "LOW < HIGH"),
        ("mu=low..high", "is not a range"),
        ("nu=0.4..0.5", r"nu must stay in \(-1, 0.5\)"),
        ("E=-1e3..1e5", r"E must stay in \[10, 1e\+09\] Pa"),
        ("E=±100%", "percentage must lie between 0 and 100"),
        ("mu=±0.9", r"mu must stay in \[0, 5\]"),
    ],
)
def test_bad_uncertain_ranges_say_what_is_wrong(text, message):
    with pytest.raises(ConfigError, match=message):
        parse_uncertain(text, NOMINAL)


def test_force_control_reaches_its_setpoints_and_holds_the_nominal_plan(sphere, nominal_plan):
    """The nominal plan's set-points, reached by force control on its own contacts, hold the
    object it was planned for: each finger within the controller's 1 % of its set-point, the
    centre of mass within 1 mm."""
    cfg = replace(nominal_plan.config, grasp=nominal_plan.initial)
    target = np.array([f.normal_force for f in nominal_plan.fingers])
    res = hold_setpoints(sphere, cfg, target)
    assert np.all(np.abs(res.reached - target) <= 0.01 * target)
    assert res.held, res.reason
    assert res.drift < 1e-3
    assert 0 < res.friction_margin < 1
    assert np.isfinite(res.held_normal).all() and res.held_normal.min() > 0
    # The increment cap counts the increments: the same closing within exactly that many.
    again = hold_setpoints(sphere, cfg, target, max_increments=res.increments)
    assert again.held and again.increments == res.increments
    short = hold_setpoints(sphere, cfg, target, max_increments=res.increments - 1)
    assert not short.held and "did not settle" in short.reason


def _squeezed_ball(k: np.ndarray, k_table: float):
    """Normal forces [N] of three fingertips at travels ``s`` [m] along their closing lines (in one
    plane, the thumb opposite the two fingers) on a rigid ball that a spring ``k_table`` [N/m]
    holds: Hertz contacts F_j = k_j p_j^1.5, the ball moved to where the forces and the spring
    balance (SciPy's root finder), so that each finger's force changes when another pushes."""
    from scipy.optimize import root

    ang = np.radians([0.0, 160.0, 200.0])
    U = np.stack([np.cos(ang), np.sin(ang)], axis=1)  # each closing direction

    def forces(s: np.ndarray) -> np.ndarray:
        def unbalanced(c):
            return (k * np.maximum(s - U @ c, 0.0) ** 1.5) @ U - k_table * c

        sol = root(unbalanced, np.zeros(2), tol=1e-13)
        assert np.abs(unbalanced(sol.x)).max() <= 1e-9 * max(k_table * np.abs(sol.x).max(), 1e-6), sol
        return k * np.maximum(s - U @ sol.x, 0.0) ** 1.5

    return forces


def test_the_force_controller_moves_the_fingers_together_to_their_set_points():
    """The controller's rule (``_next_move``) on three fingertips squeezing a ball held by a weak
    spring (each finger's force also moves when the others push): from first touch it reaches
    40 random reachable sets of set-points within 1 % in at most 8 increments of at most 0.5 mm
    (measured 6 at most; each finger's own secant gain alone needs up to 20, the corrections of
    one finger upsetting the others). A finger without a gain yet moves by the travel at which its
    contact alone meets its set-point. Working on F^(2/3), in which these Hertz contacts are
    linear, the forces pass their set-points by 1.5 % (median) and 8.8 % at most, only through the
    fingers' coupling (a secant on F itself: 6.7 % and 26 %)."""
    from softgrasp.grasp.force_control import _next_move

    step = 5e-4
    rng = np.random.default_rng(7)
    peaks = []
    for _ in range(40):
        k = rng.uniform(2e4, 6e4, 3)
        plant = _squeezed_ball(k, rng.uniform(5.0, 50.0))
        target = plant(rng.uniform(5e-4, 2e-3, 3))
        first = (target / k) ** (2 / 3)  # each contact's law alone meets its set-point there
        s, F = np.zeros(3), np.zeros(3)
        ds, dG = np.zeros(3), np.zeros(3)
        gain, jac, peak = np.full(3, np.nan), None, 0.0
        for n in range(9):
            err = target - F
            if (np.abs(err) <= 0.01 * target).all():
                break
            move, gain, jac = _next_move(ds, dG, target ** (2 / 3) - F ** (2 / 3), gain, jac, step, first)
            if n == 0:
                np.testing.assert_allclose(move, np.minimum(first, step))  # no gains yet
            assert np.abs(move).max() <= step
            move = np.clip(move, -s, None)
            F_new = plant(s + move)
            ds, dG, s, F = move, F_new ** (2 / 3) - F ** (2 / 3), s + move, F_new
            peak = max(peak, float((F / target).max()))
        assert (np.abs(target - F) <= 0.01 * target).all(), (n, target, F)
        peaks.append(peak)
    assert np.median(peaks) < 1.03 and max(peaks) < 1.10, (np.median(peaks), max(peaks))


@pytest.mark.parametrize(
    "name, contact, options",
    [
        ("cube", {}, {}),
        ("sphere", {}, {}),
        ("sphere", {"law": "paper", "exponent": 2.0}, {}),
        ("cube", {}, {"hand": "parallel_jaw"}),
    ],
)
def test_force_control_closes_on_its_set_points_without_crushing_first(name, contact, options):
    """Force control to a plan's last closing forces, on the stiff foam cube (penetrations of
    80 um) and on the soft rubber sphere (1.1 mm), under the default law, the paper's law with
    n = 2, and with the two fingers of the parallel-jaw gripper, with closing steps of 0.5 and
    1 mm: no finger presses more than 6 % past its set-point on the way (measured at most 2.1 %,
    2.7 %, 0.2 % and 0.01 %; a secant on the force itself, blind to the contact stiffening as it
    loads, pressed the cube with 14 times its set-points before backing off, by how much
    depending on the step; each finger's own secant aiming the whole way, blind to the others
    pushing the cube towards it on the table's elastic slip, 7.9 %)."""
    body = load_body(name)
    cfg = plan_config(dict(PLAN_DEFAULTS, **options), contact_params(None, 0.8, **contact))
    plan = plan_grasp(body, cfg)
    k = int(np.argmax(plan.travel))
    for step in (5e-4, 1e-3):
        res = hold_setpoints(body, replace(plan.config, grasp=plan.initial, step=step), plan.normal_force[k])
        assert res.held and res.increments <= 12, (step, res.reason, res.increments)
        assert (res.peak <= 1.06 * res.setpoints).all(), (step, res.peak / res.setpoints)
        assert (np.abs(res.reached - res.setpoints) <= 0.01 * res.setpoints).all()


def test_force_control_penetration_scales_with_stiffness_between_hertz_and_a_linear_body():
    """Run as a sweep's hold case, so that the case's E (and contact law) reach the body: the same
    set-points on a sphere four times stiffer need less penetration, by a factor between
    4^(2/3) = 2.52 (Hertz contact alone, delta ~ E^(-2/3)) and 4 (the linear elastic body alone,
    delta ~ 1/E). The paper's law, whose contact part is exactly K delta^1.5 in series with the
    body: the default law credits the mesh with a share of the compliance that depends on the
    contact radius, and so on E, and its penetrations fall by 2.38-2.51 (its departure from
    Hertz's scaling, within the 10 % of Hertz it keeps to)."""
    from softgrasp.sweep.case import run_case

    setpoints = (0.34, 0.22, 0.23)
    soft, stiff = (run_case({"E": E, "contact_law": "paper"}, hold=setpoints) for E in (40e3, 160e3))
    for row in (soft, stiff):
        assert row["status"] == "ok" and row["held"] is True, row["error"] or row["hold_reason"]
    for f in ("thumb", "first", "middle"):
        ratio = soft[f"penetration_{f}_m"] / stiff[f"penetration_{f}_m"]
        assert 4 ** (2 / 3) * 0.97 < ratio < 4.0, (f, ratio)


def test_force_control_to_the_plans_table_forces_ends_where_the_plan_closed(sphere, nominal_plan):
    """Position control and force control meet at the same equilibrium: closing under force
    control to the normal forces the plan's last increment reached on the table (at its final
    travel, by position control) brings each fingertip to that travel, within a tenth of a step."""
    plan = nominal_plan
    k = int(np.argmax(plan.travel))
    cfg = replace(plan.config, grasp=plan.initial)
    res = hold_setpoints(sphere, cfg, plan.normal_force[k])
    assert np.abs(res.travel - plan.travel[k]).max() < 0.1 * cfg.step, (res.travel, plan.travel[k])


def test_setpoints_beyond_the_crushing_limit_are_not_held_and_say_why(sphere, nominal_plan):
    cfg = replace(nominal_plan.config, grasp=nominal_plan.initial, max_squeeze=0.05)
    res = hold_setpoints(sphere, cfg, (30.0, 30.0, 30.0))
    assert not res.held and "crushing limit" in res.reason and math.isnan(res.drift)
    assert res.travel.max() == pytest.approx(res.max_travel, abs=1e-12)  # it went all the way
    with pytest.raises(ConfigError, match="normal forces > 0 N"):
        hold_setpoints(sphere, cfg, (1.0, -1.0, 1.0))


def test_a_plan_from_another_plans_grasp_keeps_its_contacts(tmp_path, sphere, nominal_plan):
    """``--grasp``: the contacts read back from plan.json give the same plan at the same
    parameters, and a lower friction on the same contacts needs more force."""
    write_json(tmp_path / "plan.json", plan_document(nominal_plan, sphere, "sphere"))
    ig = load_plan_grasp(tmp_path / "plan.json")
    np.testing.assert_allclose(ig.points, nominal_plan.initial.points, atol=1e-15)
    cfg = replace(nominal_plan.config, grasp=ig)
    again = plan_grasp(sphere, cfg)
    np.testing.assert_allclose(again.start_centres, nominal_plan.start_centres, atol=1e-12)
    np.testing.assert_allclose(
        [f.normal_force for f in again.fingers], [f.normal_force for f in nominal_plan.fingers], rtol=1e-6
    )
    slippery = plan_grasp(sphere, replace(cfg, contact=replace(cfg.contact, mu=0.5)))
    np.testing.assert_allclose(slippery.start_centres, nominal_plan.start_centres, atol=1e-12)
    assert sum(f.normal_force for f in slippery.fingers) > 1.2 * sum(f.normal_force for f in again.fingers)
    cube = load_body("cube")
    with pytest.raises(InfeasibleGrasp, match="off this object's surface"):
        plan_grasp(cube, replace(cfg, hand=None))
    doc = json.loads((tmp_path / "plan.json").read_text())
    del doc["initial_grasp"]["normals"]
    (tmp_path / "bad.json").write_text(json.dumps(doc))
    with pytest.raises(ConfigError, match="initial_grasp.normals"):
        load_plan_grasp(tmp_path / "bad.json")


#: The coarse sphere of the robust set-points' test (half the default element size).
COARSE_H = 0.032


@pytest.mark.slow
def test_robust_setpoints_hold_every_sample_where_the_nominal_ones_fail(tmp_path):
    """The issue's test: robust set-points over mu in 0.4..0.8 and E +-20 % (8 samples, planned on
    a 2-worker Dask cluster), applied by force control to the object with each sampled parameter
    set, hold it: the centre of mass moves < 1 mm. Checked again here, in this process, apart
    from the cluster's check. The nominal plan's set-points (mu = 0.8) fail for at least one
    sample, and friction, not stiffness, drives the force (more friction, less squeeze). On the
    coarse sphere: the claims are of the set-points of the object planned, whatever its mesh."""
    sphere = load_body("sphere", COARSE_H)
    options = {**PLAN_DEFAULTS, "mesh_size": COARSE_H}
    nominal_plan = plan_grasp(sphere, plan_config(options, contact_params(None, 0.8)))
    write_json(tmp_path / "grasp.json", plan_document(nominal_plan, sphere, "sphere"))
    nominal = nominal_values(sphere, 0.8)
    uncertain = [parse_uncertain("mu=0.4..0.8", nominal), parse_uncertain("E=±20%", nominal)]
    target = np.array([f.normal_force for f in nominal_plan.fingers])
    res = robust_setpoints(
        {"mu": 0.8, "mesh_size": COARSE_H},
        tmp_path / "grasp.json",
        target,
        uncertain,
        tmp_path / "robust",
        samples=8,
        seed=3,
    )
    assert res.achieved and res.held.all()
    assert np.isfinite(res.required).all()
    assert np.all(res.setpoints >= res.required.max(axis=0) - 1e-12)
    assert res.drivers[0][0] == "mu" and res.drivers[0][1] < -0.5
    cfg = replace(nominal_plan.config, grasp=nominal_plan.initial)
    nominal_failed = 0
    for i, s in enumerate(res.samples):
        body = load_body("sphere", COARSE_H, overrides={"E": s["E"]})
        c = replace(cfg, contact=replace(cfg.contact, mu=s["mu"]))
        robust = hold_setpoints(body, c, res.setpoints)
        assert robust.held, f"sample {i} {s}: {robust.reason}"
        assert robust.drift < 1e-3
        if not nominal_failed:  # one sample the nominal set-points drop is the claim: no need for more
            nominal_failed += not hold_setpoints(body, c, target).held
    assert nominal_failed >= 1 and res.nominal_failure_fraction > 0


@pytest.mark.slow
def test_plan_uncertain_command_writes_robust_setpoints(tmp_path, capsys):
    out = tmp_path / "plan"
    args = ["plan", "--out", str(out), "--uncertain", "mu=0.5..0.8", "--samples", "4", "--quantile", "0.5"]
    args += ["--mesh-size", str(COARSE_H)]  # the coarse sphere: what is checked needs no finer one
    assert main(args) == 0
    text = capsys.readouterr().out
    assert "what drives the set-points" in text and "mu (rho" in text
    plan = json.loads((out / "plan.json").read_text())
    robust = json.loads((out / "robust.json").read_text())
    assert plan["setpoints"] == "robust" and robust["achieved"] and robust["held_fraction"] >= 0.5
    need = np.array([s["required_N"] for s in robust["per_sample"]])
    median = np.quantile(need, 0.5, axis=0, method="higher") * robust["scale_over_samples"]
    for j, f in enumerate(plan["fingers"]):
        assert f["setpoint_N"] == plan["setpoints_N"][f["name"]] == pytest.approx(median[j], rel=1e-12)
        assert f["nominal_setpoint_N"] == robust["nominal_setpoints_N"][f["name"]]
    # Every sample's friction is below the nominal 0.8: every one needs more squeeze.
    assert need.sum(axis=1).min() > sum(f["nominal_setpoint_N"] for f in plan["fingers"])
    for stage in ("samples", "nominal", "robust-1"):
        assert (out / "robust" / stage / "results.parquet").is_file()
    assert (out / "robust.png").stat().st_size > 10_000
    assert not (out / ".robust-partial").exists()
    # A plain plan into the same folder takes the robust outputs, which no longer belong, away.
    assert main(["plan", "--out", str(out), "--mesh-size", str(COARSE_H)]) == 0
    assert not (out / "robust.json").exists() and not (out / "robust").exists()
    assert "robust" not in json.loads((out / "plan.json").read_text())


def test_sample_requirements_tell_an_unholdable_sample_from_a_failed_solve():
    rows = [
        {"status": "ok", "setpoint_thumb_N": 0.4, "setpoint_first_N": 0.3, "setpoint_middle_N": 0.3},
        {"status": "failed", "error": "no hold before the maximum squeeze", "error_type": "InfeasibleGrasp"},
    ] + [
        {"status": "ok", "setpoint_thumb_N": 0.4 + k, "setpoint_first_N": 0.3, "setpoint_middle_N": 0.3}
        for k in range(8)
    ]
    options = [{"mu": 0.1 * (i + 1)} for i in range(len(rows))]
    required, errors = sample_requirements(rows, options, ["mu"])
    assert np.isinf(required[1]).all() and np.isfinite(np.delete(required, 1, axis=0)).all()
    assert errors[1].startswith("no hold") and errors[0] == ""
    # The quantile the message offers is the largest that leaves the unholdable sample out.
    text = _unholdable(required, errors, options, ["mu"], None)
    q = float(text.rsplit("--quantile ", 1)[1].split()[0])
    assert np.isfinite(np.quantile(required, q, axis=0, method="higher")).all()
    assert not np.isfinite(np.quantile(required, q + 0.01, axis=0, method="higher")).all()
    rows[2] = {"status": "failed", "error": "static solve cycles", "error_type": "NotConverged"}
    with pytest.raises(NotConverged, match="sample 2 \\(mu = 0.3\\) could not be planned"):
        sample_requirements(rows, options, ["mu"])


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--quantile", "0.9"], "--quantile applies to robust set-points"),
        (["--samples", "8"], "--samples applies to robust set-points"),
        (["--uncertain", "nu=0.4..0.55"], "nu must stay"),
        (["--uncertain", "mu=0.4..0.8", "--uncertain", "mu=±0.1"], "gives a parameter twice"),
        (["--uncertain", "mu=0.4..0.8", "--samples", "1"], "--samples must be an integer from 2 to 100000"),
        (["--uncertain", "mu=0.4..0.8", "--quantile", "1.5"], "--quantile must be a number in (0, 1)"),
    ],
)
def test_plan_uncertain_refuses_bad_options_before_planning(tmp_path, capsys, extra, message):
    assert main(["plan", "--out", str(tmp_path / "p"), *extra]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "p").exists()
