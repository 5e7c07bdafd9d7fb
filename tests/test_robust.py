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
from softgrasp.errors import ConfigError, InfeasibleGrasp
from softgrasp.grasp.force_control import hold_setpoints
from softgrasp.grasp.options import PLAN_DEFAULTS, contact_params, load_body, plan_config
from softgrasp.grasp.planner import plan_grasp
from softgrasp.grasp.report import plan_document
from softgrasp.grasp.robust import nominal_values, parse_uncertain, robust_setpoints
from softgrasp.hand.planfile import load_plan_grasp
from softgrasp.output import write_json

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
        ("nu=0.4..0.5", "nu must stay > -1 and < 0.5"),
        ("E=-1e3..1e5", "E must stay > 0"),
        ("E=±100%", "percentage must lie between 0 and 100"),
        ("mu=±0.9", "mu must stay >= 0"),
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
    # The held state's forces balance the weight (Eq. 21): their sum's vertical part is the weight.
    assert res.held_normal.min() > 0


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
    with pytest.raises(ConfigError, match="three normal forces > 0 N"):
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


@pytest.mark.slow
def test_robust_setpoints_hold_every_sample_where_the_nominal_ones_fail(tmp_path, sphere, nominal_plan):
    """The issue's test: robust set-points over mu in 0.4..0.8 and E +-20 % (8 samples, planned on
    a 2-worker Dask cluster), applied by force control to the object with each sampled parameter
    set, hold it: the centre of mass moves < 1 mm. Checked again here, in this process, apart
    from the cluster's check. The nominal plan's set-points (mu = 0.8) fail for at least one
    sample, and friction, not stiffness, drives the force (more friction, less squeeze)."""
    write_json(tmp_path / "grasp.json", plan_document(nominal_plan, sphere, "sphere"))
    nominal = nominal_values(sphere, 0.8)
    uncertain = [parse_uncertain("mu=0.4..0.8", nominal), parse_uncertain("E=±20%", nominal)]
    target = np.array([f.normal_force for f in nominal_plan.fingers])
    res = robust_setpoints(
        {"mu": 0.8}, tmp_path / "grasp.json", target, uncertain, tmp_path / "robust", samples=8, seed=3
    )
    assert res.achieved and res.held.all()
    assert np.isfinite(res.required).all()
    assert np.all(res.setpoints >= res.required.max(axis=0) - 1e-12)
    assert res.drivers[0][0] == "mu" and res.drivers[0][1] < -0.5
    cfg = replace(nominal_plan.config, grasp=nominal_plan.initial)
    nominal_failed = 0
    for i, s in enumerate(res.samples):
        body = load_body("sphere", overrides={"E": s["E"]})
        c = replace(cfg, contact=replace(cfg.contact, mu=s["mu"]))
        robust = hold_setpoints(body, c, res.setpoints)
        assert robust.held, f"sample {i} {s}: {robust.reason}"
        assert robust.drift < 1e-3
        nominal_failed += not hold_setpoints(body, c, target).held
    assert nominal_failed >= 1 and res.nominal_failure_fraction > 0


@pytest.mark.slow
def test_plan_uncertain_command_writes_robust_setpoints(tmp_path, capsys):
    out = tmp_path / "plan"
    args = ["plan", "--out", str(out), "--uncertain", "mu=0.5..0.8", "--samples", "4", "--quantile", "0.5"]
    assert main(args) == 0
    text = capsys.readouterr().out
    assert "what drives the set-points" in text and "mu (rho" in text
    plan = json.loads((out / "plan.json").read_text())
    robust = json.loads((out / "robust.json").read_text())
    assert plan["setpoints"] == "robust" and robust["achieved"] and robust["held_fraction"] >= 0.5
    need = np.array([s["required_N"] for s in robust["per_sample"]])
    for j, f in enumerate(plan["fingers"]):
        assert f["normal_force_N"] == robust["setpoints_N"][f["name"]]
        assert f["nominal_normal_force_N"] == robust["nominal_setpoints_N"][f["name"]]
        assert f["normal_force_N"] <= need[:, j].max() * robust["scale_over_samples"] + 1e-12
    for stage in ("samples", "nominal", "robust-1"):
        assert (out / "robust" / stage / "results.parquet").is_file()
    assert (out / "robust.png").stat().st_size > 10_000
    assert not (out / ".robust-partial").exists()


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--quantile", "0.9"], "--quantile applies to robust set-points"),
        (["--uncertain", "nu=0.4..0.55"], "nu must stay"),
        (["--uncertain", "mu=0.4..0.8", "--uncertain", "mu=±0.1"], "gives a parameter twice"),
        (["--uncertain", "mu=0.4..0.8", "--samples", "1"], "--samples must be from 2"),
        (["--uncertain", "mu=0.4..0.8", "--quantile", "1.5"], "--quantile must lie between 0 and 1"),
    ],
)
def test_plan_uncertain_refuses_bad_options_before_planning(tmp_path, capsys, extra, message):
    assert main(["plan", "--out", str(tmp_path / "p"), *extra]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "p").exists()
