"""``softgrasp execute`` on MuJoCo (physics softgrasp did not write): the default plan's set-points
are reached by force control, the sphere is lifted without slipping, a quarter of the set-points
lets it go; plan files that cannot be executed are refused clearly."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest

from softgrasp.cli import main
from softgrasp.errors import ConfigError
from softgrasp.io.planfile import load_plan_file


@pytest.fixture(scope="module")
def plan_dir(planned_sphere) -> Path:
    # The least squeeze that holds in softgrasp's model (safety factor 1) sits at the edge of
    # holding; MuJoCo's contact needs a few per cent more: the plan has a margin (conftest).
    return planned_sphere


@pytest.fixture(scope="module")
def full(plan_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("execute")
    rc = main(["execute", str(plan_dir / "plan.json"), "--out", str(out)])
    return rc, json.loads((out / "execute.json").read_text()), out


@pytest.mark.slow
def test_plan_set_points_with_a_margin_are_reached_and_the_sphere_lifted(full):
    rc, doc, out = full
    assert rc == 0
    assert doc["schema"] == "softgrasp.execute/1"
    assert doc["reached"]
    for f in doc["fingers"]:
        assert abs(f["error_N"]) <= 0.05 * f["setpoint_N"], f
    assert doc["lifted"] and not doc["dropped"]
    assert doc["rise_m"] > 0.09  # the 0.10 m lift, less the object's sag in the fingers
    assert doc["slip_m"] < 0.005
    rows = (out / "execute.csv").read_text().splitlines()
    assert rows[0].startswith("t_s,phase,base_rise_m,com_x_m,com_y_m,com_z_m,thumb_normal_force_N")
    assert len(rows) > 1000  # 2 ms control periods over > 4 s
    for name in (
        "execute_forces.png",
        "frame_start.png",
        "frame_contact.png",
        "frame_closed.png",
        "frame_end.png",
    ):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.slow
def test_a_quarter_of_the_set_points_slips_more_than_the_full_plan(plan_dir, full, tmp_path):
    _, doc_full, _ = full
    argv = ["execute", str(plan_dir / "plan.json"), "--scale", "0.25", "--hold", "0.5"]
    rc = main([*argv, "--out", str(tmp_path)])  # (it drops in the lift: a short hold after it)
    doc = json.loads((tmp_path / "execute.json").read_text())
    assert [f["setpoint_N"] for f in doc["fingers"]] == pytest.approx(
        [0.25 * f["setpoint_N"] for f in doc_full["fingers"]]
    )
    assert doc["slip_m"] > doc_full["slip_m"]
    # The plan holds at close to the least squeeze (17 % friction margin): a quarter lets it go.
    assert doc["dropped"] and not doc["lifted"]
    assert rc == 1  # the exit status tells a script the object fell


def _write(tmp_path: Path, doc: dict, plan_dir: Path) -> Path:
    p = tmp_path / "plan.json"
    p.write_text(json.dumps(doc))
    (tmp_path / "object.vtu").write_bytes((plan_dir / "object.vtu").read_bytes())
    return p


@pytest.mark.parametrize(
    "edit, needle",
    [
        (
            lambda d: d.update(schema="softgrasp.plan/0"),
            "schema 'softgrasp.plan/0' is not 'softgrasp.plan/2'",
        ),
        (lambda d: d["object"].pop("mass_kg"), "missing field 'object.mass_kg'"),
        (lambda d: d["object"].update(mass_kg=-0.05), "'object.mass_kg' = -0.05 kg is not physical"),
        (lambda d: d["object"]["material"].update(nu=0.5), "'object.material.nu' = 0.5 is not physical"),
        (
            lambda d: d["object"]["material"].update(E_Pa="soft"),
            "'object.material.E_Pa' must be a finite number",
        ),
        (
            lambda d: d["fingers"][0].update(setpoint_N=float("nan")),
            "setpoint_N' must be a finite number",
        ),
        (lambda d: d["fingers"][1].update(setpoint_N=0.0), "setpoint_N' = 0 N is not physical"),
        (lambda d: d["fingers"][2].pop("start_position_m"), r"missing field 'fingers\[2\].start_position_m'"),
        (lambda d: d.update(hand=None), "made without a hand model"),
        (lambda d: d["hand"].update(palm_pose=np.diag([2.0, 1, 1, 1]).tolist()), "not a rigid transform"),
        (lambda d: d["object"].update(mesh_file="nowhere.vtu"), "object mesh .*nowhere.vtu is missing"),
    ],
)
def test_plan_files_that_cannot_be_executed_are_refused(plan_dir, tmp_path, capsys, edit, needle):
    doc = copy.deepcopy(json.loads((plan_dir / "plan.json").read_text()))
    edit(doc)
    path = _write(tmp_path, doc, plan_dir)
    with pytest.raises(ConfigError, match=needle):
        load_plan_file(path)
    assert main(["execute", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "softgrasp: error: plan file" in err and "Traceback" not in err
    assert not (tmp_path / "out" / "execute.json").exists()


def test_execute_refuses_bad_options_and_missing_files(tmp_path, capsys):
    assert main(["execute", str(tmp_path / "missing.json")]) == 2
    assert "does not exist" in capsys.readouterr().err
    (tmp_path / "p.json").write_text("{not json")
    assert main(["execute", str(tmp_path / "p.json")]) == 2
    assert "not readable JSON" in capsys.readouterr().err
    assert main(["execute", str(tmp_path / "p.json"), "--scale", "-1"]) == 2
    assert "--scale = -1 is not physical: it must be 0 < --scale <= 10" in capsys.readouterr().err
