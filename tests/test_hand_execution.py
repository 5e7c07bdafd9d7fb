"""Any hand through execution, robust set-points and sweeps: a parallel-jaw plan and an MJCF-hand
plan execute in MuJoCo and reach their set-points; robust set-points and a sweep's rows name the
plan's own fingers (``left``/``right`` for the gripper), and a sweep of hands with different
fingers is refused at the door."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

import softgrasp as sg
from softgrasp.cli import main
from softgrasp.errors import ConfigError
from softgrasp.sweep.case import output_columns, run_case
from softgrasp.sweep.robust import sample_requirements
from softgrasp.sweep.spec import SweepSpec, read_sweep

DATA = Path(__file__).parent / "data"
MJCF = DATA / "three_finger_hand.xml"
MJCF_TIPS = "thumb=th_distal,first=ff_distal,middle=mf_distal"
#: A coarse rubber ball the gripper holds: a plan of a few seconds.
BALL = ("ball:0.03", "rubber", 0.015)


def _sweep(tmp_path: Path, base: str, grid: str = 'mu = [0.6, 0.8]') -> Path:
    path = tmp_path / "s.toml"
    path.write_text(f"[sweep]\nmode = 'grid'\n\n[base]\n{base}\n\n[grid]\n{grid}\n", encoding="utf-8")
    return path


# ---------------------------------------------------------------------- at the door (fast)


def test_a_sweeps_columns_name_its_hands_fingers(tmp_path: Path) -> None:
    jaw = read_sweep(_sweep(tmp_path, 'hand = "parallel_jaw"'))
    assert jaw.fingers == ("left", "right")
    cols = output_columns(False, fingers=jaw.fingers)
    assert "setpoint_left_N" in cols and "penetration_right_m" in cols
    assert not any("thumb" in c for c in cols)
    hold = output_columns(False, True, jaw.fingers)
    assert {"reached_left_N", "held_right_N"} <= set(hold) and "held_thumb_N" not in hold
    assert read_sweep(_sweep(tmp_path, 'object = "cube"')).fingers == ("thumb", "first", "middle")


def test_a_sweep_over_hands_with_different_fingers_is_refused(tmp_path: Path) -> None:
    path = _sweep(tmp_path, 'object = "cube"', 'hand = ["shadow_like", "parallel_jaw"]')
    with pytest.raises(ConfigError, match=r"s\.toml: the hands plan with different fingers .*parallel_jaw "
                       r"plans with left, right.*sweep each hand apart"):
        read_sweep(path)


def test_a_sweep_with_an_unreadable_hand_names_the_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"sweep file .*s\.toml: hand '.*nohand\.urdf'"):
        read_sweep(_sweep(tmp_path, f'hand = "{tmp_path / "nohand.urdf"}"'))


def test_hold_setpoints_are_one_per_finger() -> None:
    with pytest.raises(ConfigError, match=r"one per finger \(left, right\)"):
        SweepSpec("grid", 1, 0, False, hold=(0.3, 0.3, 0.3), fingers=("left", "right"))


def test_a_case_whose_hand_has_other_fingers_than_the_columns_fails_with_the_reason() -> None:
    row = run_case({"object": "cube", "hand": "parallel_jaw"}, fingers=("thumb", "first", "middle"))
    assert row["status"] == "failed" and row["error_type"] == "ConfigError"
    assert "plans with the fingers left, right" in str(row["error"])
    assert set(row) == set(output_columns(False))


def test_sample_requirements_read_the_grippers_columns() -> None:
    rows = [{"status": "ok", "setpoint_left_N": 0.4 + k, "setpoint_right_N": 0.5} for k in range(3)]
    required, errors = sample_requirements(rows, [{"mu": 0.5}] * 3, ["mu"], ("left", "right"))
    assert required.shape == (3, 2) and errors == ["", "", ""]
    np.testing.assert_allclose(required[:, 0], [0.4, 1.4, 2.4])


def test_a_sweep_of_the_gripper_writes_its_fingers_rows_and_figure(tmp_path: Path, capsys) -> None:
    source, material, size = BALL
    base = f'object = "{source}"\nmaterial = "{material}"\nmesh_size = {size}\nhand = "parallel_jaw"'
    out = tmp_path / "sweep"
    path = _sweep(tmp_path, base, "mu = [0.7, 0.8]")
    assert main(["sweep", str(path), "--workers", "1", "--out", str(out)]) == 0
    with open(out / "results.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["status"] for r in rows] == ["ok", "ok"]
    for r in rows:
        assert float(r["setpoint_left_N"]) > 0 and float(r["setpoint_right_N"]) > 0
        both = float(r["setpoint_left_N"]) + float(r["setpoint_right_N"])
        assert float(r["setpoint_sum_N"]) == pytest.approx(both)
    assert json.loads((out / "sweep.json").read_text())["fingers"] == ["left", "right"]
    assert (out / "force_vs_mu.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


# ---------------------------------------------------------------------- execution in MuJoCo


@pytest.mark.slow
def test_a_parallel_jaw_plan_executes_in_mujoco_and_reaches_its_setpoints(tmp_path: Path) -> None:
    pytest.importorskip("mujoco")
    source, material, size = BALL
    out = tmp_path / "plan"
    args = ["plan", "--object", source, "--material", material, "--mesh-size", str(size)]
    assert main([*args, "--hand", "parallel_jaw", "--out", str(out)]) == 0
    assert main(["execute", str(out), "--lift", "0.03", "--out", str(tmp_path / "run")]) == 0
    doc = json.loads((tmp_path / "run" / "execute.json").read_text())
    assert [f["name"] for f in doc["fingers"]] == ["left", "right"]
    assert doc["reached"] and doc["lifted"] and not doc["dropped"]
    for f in doc["fingers"]:
        assert abs(f["error_N"]) <= 0.05 * f["setpoint_N"], f
    assert doc["rise_m"] > 0.02 and doc["slip_m"] < 0.005
    head = (tmp_path / "run" / "execute.csv").read_text().splitlines()[0]
    assert "left_normal_force_N" in head and "right_travel_m" in head and "thumb" not in head


@pytest.mark.slow
def test_an_mjcf_hand_plan_executes_in_mujoco_and_reaches_its_setpoints() -> None:
    pytest.importorskip("mujoco")
    result = sg.plan("sphere", hand=str(MJCF), fingertips=MJCF_TIPS)
    run = sg.execute(result, lift_m=0.03, hold_s=0.5)
    doc = run.document
    assert [f["name"] for f in doc["fingers"]] == ["thumb", "first", "middle"]
    assert doc["reached"] and doc["lifted"]
    for f in doc["fingers"]:
        assert abs(f["error_N"]) <= 0.05 * f["setpoint_N"], f


# ---------------------------------------------------------------------- robust set-points


@pytest.mark.slow
def test_robust_setpoints_of_a_gripper_name_its_fingers(tmp_path: Path) -> None:
    source, material, size = BALL
    out = tmp_path / "plan"
    args = ["plan", "--object", source, "--material", material, "--mesh-size", str(size), "--hand"]
    args += ["parallel_jaw", "--uncertain", "mu=0.7..0.8", "--samples", "2", "--out", str(out)]
    assert main(args) == 0
    plan = json.loads((out / "plan.json").read_text())
    robust = json.loads((out / "robust.json").read_text())
    assert plan["setpoints"] == "robust" and robust["fingers"] == ["left", "right"]
    assert set(robust["setpoints_N"]) == set(robust["nominal_setpoints_N"]) == {"left", "right"}
    assert all(len(s["required_N"]) == 2 for s in robust["per_sample"])
    for f in plan["fingers"]:
        assert f["setpoint_N"] == plan["setpoints_N"][f["name"]] == robust["setpoints_N"][f["name"]]
    for stage in ("samples", "nominal", "robust-1"):
        head = (out / "robust" / stage / "results.csv").read_text().splitlines()[0].split(",")
        assert not any("thumb" in c for c in head)
        want = "setpoint_left_N" if stage == "samples" else "held_left_N"
        assert want in head and want.replace("left", "right") in head


@pytest.mark.slow
def test_robust_setpoints_of_an_mjcf_hand_plan_run_on_its_hand_file(tmp_path: Path) -> None:
    pytest.importorskip("mujoco")
    from softgrasp.api.robust import robust_plan, uncertain_parameters

    source, material, size = BALL
    obj = sg.load_object(source, material=material, mesh_size_m=size)
    result = sg.plan(obj, hand=str(MJCF), fingertips=MJCF_TIPS)
    result.save(tmp_path / "plan")
    res = robust_plan(result, uncertain_parameters(obj, 0.8, ["mu=0.7..0.8"], samples=2), samples=2)
    assert res.fingers == ("thumb", "first", "middle") and res.required.shape == (2, 3)
    doc = json.loads((tmp_path / "plan" / "robust.json").read_text())
    assert list(doc["setpoints_N"]) == ["thumb", "first", "middle"]
    with open(tmp_path / "plan" / "robust" / "samples" / "results.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["status"] for r in rows] == ["ok", "ok"]
    assert all(r["hand"].endswith("three_finger_hand.xml") and r["fingertips"] == MJCF_TIPS for r in rows)
    assert all(float(r["setpoint_middle_N"]) > 0 for r in rows)
