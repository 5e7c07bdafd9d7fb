"""``softgrasp execute`` ends, and refuses what it cannot execute: options and plan.json fields
outside their physical ranges, plans whose parts disagree (fingers, object mesh, hand, palm pose)
are refused before anything is simulated; a simulation that blows up, a stuck clock and a run past
its wall-clock bound stop with a clear error; MuJoCo writes no log into the working folder; a
Ctrl-C ends every command with one line and exit status 130."""

from __future__ import annotations

import copy
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from softgrasp.cli import main
from softgrasp.errors import ConfigError, SimulationUnstable
from softgrasp.execution.controller import ExecuteConfig, execute_plan
from softgrasp.io.planfile import load_plan_file
from test_execute import SpringHand, lines_for

SRC = str(Path(__file__).resolve().parents[1] / "src")


@pytest.fixture
def no_simulation(monkeypatch):
    """Any MuJoCo scene built from here on fails the test: a refusal must come before it."""

    def refuse(spec):
        raise AssertionError("a MuJoCo scene was built for a plan that should have been refused")

    monkeypatch.setattr("softgrasp.execution.mujoco.hand.load_scene", refuse)


def _doc(planned: Path) -> dict:
    return copy.deepcopy(json.loads((planned / "plan.json").read_text()))


def _tampered(tmp_path: Path, planned: Path, doc: dict, mesh: bytes | None = None) -> Path:
    p = tmp_path / "plan.json"
    p.write_text(json.dumps(doc))
    (tmp_path / "object.vtu").write_bytes(mesh if mesh is not None else (planned / "object.vtu").read_bytes())
    return p


def _refused(capsys, argv: list[str], needle: str) -> None:
    t0 = time.perf_counter()
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert needle in err, err
    assert err.count("\n") == 1 and err.startswith("softgrasp: error:") and "Traceback" not in err
    assert time.perf_counter() - t0 < 60  # a bound against a hang, not a timing


# ------------------------------------------------------------------ options at the door
@pytest.mark.parametrize(
    ("option", "value", "needle"),
    [
        ("--lift", "1e300", "--lift = 1e+300 m is not physical: it must be 0 < --lift <= 0.5 m"),
        ("--lift", "0", "--lift = 0 m is not physical"),
        ("--lift", "inf", "--lift must be a finite number"),
        ("--hold", "-1", "--hold = -1 s is not physical: it must be 0 <= --hold <= 60 s"),
        ("--hold", "1e4", "--hold = 10000 s is not physical"),
        ("--scale", "1e300", "--scale = 1e+300 is not physical: it must be 0 < --scale <= 10"),
        ("--scale", "nan", "--scale must be a finite number"),
        ("--scale", "0", "--scale = 0 is not physical"),
    ],
)
def test_execute_options_outside_their_range_are_refused(
    planned_sphere, tmp_path, capsys, no_simulation, option, value, needle
):
    out = tmp_path / "out"
    _refused(capsys, ["execute", str(planned_sphere / "plan.json"), option, value, "--out", str(out)], needle)
    assert not out.exists()


def test_a_scaled_set_point_beyond_a_fingertip_is_refused(planned_sphere, tmp_path, capsys, no_simulation):
    doc = _doc(planned_sphere)
    doc["fingers"][0]["setpoint_N"] = 40.0
    path = _tampered(tmp_path, planned_sphere, doc)
    _refused(capsys, ["execute", str(path), "--scale", "3", "--out", str(tmp_path / "o")], "press 120 N")


def test_execute_help_states_the_ranges(capsys):
    assert main(["execute", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "0 < LIFT <= 0.5 m" in text and "0 < SCALE <= 10" in text and "<= 100 N" in text


def test_a_material_file_outside_the_ranges_is_refused(planned_sphere, tmp_path, capsys, no_simulation):
    mf = tmp_path / "m.toml"
    mf.write_text('[material]\nname = "stone"\nE_Pa = 1e300\nnu = 0.3\n')
    _refused(
        capsys,
        ["execute", str(planned_sphere / "plan.json"), "--material", str(mf), "--out", str(tmp_path / "o")],
        f"material file {mf}: Young's modulus E = 1e+300 Pa is invalid",
    )
    mf.write_text('[material]\nname = "rubber"\nE_Pa = 8e4\nnu = 0.45\n[contact]\nmu = 1e300\n')
    _refused(
        capsys,
        ["execute", str(planned_sphere / "plan.json"), "--material", str(mf), "--out", str(tmp_path / "o")],
        "contact parameter mu = 1e+300 is invalid",
    )


# ------------------------------------------------------------- plan.json at the door
def _swap_names(d: dict) -> None:
    f = d["fingers"]
    f[0]["name"], f[1]["name"] = f[1]["name"], f[0]["name"]


def _move_palm(d: dict) -> None:
    d["hand"]["palm_pose"][0][3] += 1e6


def _move_everything(d: dict) -> None:
    d["hand"]["palm_pose"][0][3] += 1.0
    for f in d["fingers"]:
        for key in ("start_position_m", "final_position_m"):
            f[key][0] += 1.0


def _rename_joint(d: dict) -> None:
    d["hand"]["fingers"]["thumb"]["joints"][0] = "J9"


TAMPERED = [
    (
        lambda d: d["fingers"].__setitem__(1, copy.deepcopy(d["fingers"][0])),
        "'fingers[1].name': finger 'thumb' appears twice",
    ),
    (
        lambda d: d["fingers"].append({**copy.deepcopy(d["fingers"][0]), "name": "ring"}),
        "'fingers[3].name' = 'ring' is not a finger",
    ),
    (
        lambda d: d["fingers"].append(copy.deepcopy(d["fingers"][2])),
        "'fingers[3].name': finger 'middle' appears twice",
    ),
    (lambda d: d["fingers"].pop(2), "field 'fingers' lacks the finger(s) middle"),
    (_swap_names, "'fingers[0].start_position_m' is"),
    (_move_palm, "field 'hand.palm_pose' puts the palm 1e+06 m from where"),
    (_move_everything, "'fingers[0].start_position_m' lies 9"),
    (_rename_joint, "'hand.fingers.thumb.joints'"),
    (
        lambda d: d["object"]["material"].update(E_Pa=1e300),
        "'object.material.E_Pa' = 1e+300 Pa is not physical",
    ),
    (lambda d: d["object"]["material"].update(E_Pa=1.0), "'object.material.E_Pa' = 1 Pa is not physical"),
    (
        lambda d: d["parameters"]["contact"].update(mu=1e300),
        "'parameters.contact.mu' = 1e+300 is not physical",
    ),
    (lambda d: d["object"].update(mass_kg=1e300), "'object.mass_kg' = 1e+300 kg is not physical"),
    (lambda d: d["object"]["material"].update(nu=-0.2), "'object.material.nu' = -0.2 is not physical"),
    (lambda d: d["parameters"].update(fingertip_radius_m=1.0), "'parameters.fingertip_radius_m' = 1 m"),
    (lambda d: d["parameters"].update(table_mu=-1), "'parameters.table_mu' = -1 is not physical"),
    (lambda d: d["fingers"][2].update(setpoint_N=1e300), "'fingers[2].setpoint_N' = 1e+300 N"),
    (lambda d: d["object"].pop("mesh_sha256"), "missing field 'object.mesh_sha256'"),
    (lambda d: d["fingers"][0].pop("final_position_m"), "missing field 'fingers[0].final_position_m'"),
    (lambda d: d["object"].update(mesh_sha256=5), "'object.mesh_sha256' must be"),
    (lambda d: d["object"]["material"].update(E_Pa="soft"), "'object.material.E_Pa' must be a finite number"),
    (lambda d: d.update(fingers="thumb"), "'fingers' must be a non-empty list"),
    (lambda d: d["hand"].update(model=5), "'hand.model' must be a non-empty string"),
    (lambda d: d["hand"].update(palm_pose="up"), "'hand.palm_pose' must be a 4 x 4 matrix"),
    (
        lambda d: d["fingers"][1].update(start_position_m=[0.0, "x", 0.0]),
        "'fingers[1].start_position_m' must be 3",
    ),
    (
        lambda d: d["hand"]["fingers"]["first"].update(q_start_rad=[0.0]),
        "'hand.fingers.first.q_start_rad' must hold 3",
    ),
]


@pytest.mark.parametrize(("edit", "needle"), TAMPERED)
def test_a_tampered_plan_is_refused_before_simulating(
    planned_sphere, tmp_path, capsys, no_simulation, edit, needle
):
    doc = _doc(planned_sphere)
    edit(doc)
    path = _tampered(tmp_path, planned_sphere, doc)
    _refused(capsys, ["execute", str(path), "--out", str(tmp_path / "out")], needle)
    assert not (tmp_path / "out").exists()


def test_swapped_fingers_are_named_as_such(planned_sphere, tmp_path, capsys, no_simulation):
    doc = _doc(planned_sphere)
    _swap_names(doc)
    _refused(
        capsys,
        ["execute", str(_tampered(tmp_path, planned_sphere, doc)), "--out", str(tmp_path / "o")],
        "where fingers[1] starts: fingers swapped?",
    )


def test_another_object_mesh_is_refused(planned_sphere, tmp_path, capsys, no_simulation):
    from softgrasp.model.mesh.io import load_mesh, save_mesh
    from softgrasp.model.mesh.tetmesh import TetMesh

    mesh = load_mesh(planned_sphere / "object.vtu")
    other = tmp_path / "other.vtu"
    save_mesh(TetMesh(mesh.points * np.array([1.0, 1.0, 1.01]), mesh.tets), other)
    path = _tampered(tmp_path, planned_sphere, _doc(planned_sphere), other.read_bytes())
    _refused(
        capsys,
        ["execute", str(path), "--out", str(tmp_path / "out")],
        "the object mesh object.vtu is not the one planned",
    )


def test_the_plan_records_the_placed_mesh_fingerprint(planned_sphere):
    from softgrasp.execution.plan_check import check_plan
    from softgrasp.io.plan_document import mesh_digest

    plan = load_plan_file(planned_sphere / "plan.json")
    hand, mesh = check_plan(plan)
    assert plan.mesh_sha256 == mesh_digest(mesh.points, mesh.tets)
    assert mesh_digest(mesh.points[::-1], mesh.tets) != plan.mesh_sha256
    assert set(hand.fingers) >= {f.name for f in plan.fingers}


# ------------------------------------------------------------- bounds on a running execution
def test_a_blow_up_in_mujoco_stops_at_once_and_leaves_no_log(planned_sphere, tmp_path, monkeypatch):
    from softgrasp.execution.mujoco.hand import MujocoHand

    monkeypatch.chdir(tmp_path)
    hand = MujocoHand.from_plan(load_plan_file(planned_sphere / "plan.json"))
    hand.step(0.002)
    hand.scene.data.qvel[:] = np.inf  # what a far too stiff object does to the state
    with pytest.raises(SimulationUnstable) as exc:
        hand.step(0.002)
    msg = str(exc.value)
    assert "MuJoCo's simulation became unstable after t = 0.002 s" in msg
    assert "object.material.E_Pa" in msg and "parameters.contact.mu" in msg
    assert not (tmp_path / "MUJOCO_LOG.TXT").exists()
    assert list(tmp_path.iterdir()) == []


class StuckHand(SpringHand):
    """A hand whose clock stops (a simulation that keeps resetting itself, a frozen driver)."""

    def step(self, dt):
        super().step(dt)
        if self.t > 0.1:
            self.t = 0.1


def test_a_stuck_clock_ends_the_execution():
    hand = StuckHand()
    t0 = time.perf_counter()
    with pytest.raises(SimulationUnstable, match="clock did not advance"):
        execute_plan(hand, lines_for(hand, 0.3), ExecuteConfig(lift=0.05, hold_time=0.5))
    assert time.perf_counter() - t0 < 60


def test_the_wall_clock_bound_ends_the_execution():
    hand = SpringHand()
    with pytest.raises(SimulationUnstable, match=r"wall-clock time .*\(limit 1e-09 s"):
        execute_plan(hand, lines_for(hand, 0.3), ExecuteConfig(lift=0.05, max_wall_time=1e-9))
    cfg = ExecuteConfig()
    assert cfg.wall_limit == pytest.approx(60 + 100 * cfg.duration)
    assert cfg.describe()["wall_limit_s"] == cfg.wall_limit


def test_an_execution_longer_than_the_time_limit_is_refused():
    with pytest.raises(ConfigError, match="would last .* more than 300 s"):
        ExecuteConfig(hold_time=1e300)
    with pytest.raises(ConfigError, match="max_wall_time"):
        ExecuteConfig(max_wall_time=float("nan"))


# ------------------------------------------------------------------------------ Ctrl-C
def _interrupt(argv: list[str], cwd: Path, ready) -> subprocess.CompletedProcess:
    """Run ``softgrasp argv`` in its own process group, send the group SIGINT (a Ctrl-C at a
    terminal) once ``ready()`` is true, and return how it ended; fail if any process of the group
    is left behind."""
    env = {**os.environ, "PYTHONPATH": SRC}
    p = subprocess.Popen(
        [sys.executable, "-m", "softgrasp", *argv],
        cwd=cwd,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        start_new_session=True,
    )
    try:
        deadline = time.monotonic() + 240
        while not ready() and p.poll() is None and time.monotonic() < deadline:
            time.sleep(0.2)
        assert p.poll() is None, "the command ended before it could be interrupted"
        os.killpg(p.pid, signal.SIGINT)
        out, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.communicate()
    for _ in range(50):  # children exit with their parent (zombies are reaped by init)
        left = subprocess.run(["pgrep", "-g", str(p.pid)], capture_output=True, text=True).stdout.split()
        if not left:
            break
        time.sleep(0.2)
    assert not left, f"processes left behind: {left}"
    return subprocess.CompletedProcess(argv, p.returncode, out.decode(), err.decode())


def _after(seconds: float):
    t0 = time.monotonic()
    return lambda: time.monotonic() - t0 >= seconds


def _assert_interrupted(run: subprocess.CompletedProcess) -> None:
    assert run.returncode == 130, run.stderr
    assert "Traceback" not in run.stderr, run.stderr
    assert run.stderr.strip().splitlines()[-1] == "softgrasp: interrupted", run.stderr
    assert "KeyboardInterrupt" not in run.stderr


def test_ctrl_c_in_execute_is_one_line(planned_sphere, tmp_path):
    run = _interrupt(["execute", str(planned_sphere / "plan.json"), "--out", "e"], tmp_path, _after(4))
    _assert_interrupted(run)
    assert not (tmp_path / "MUJOCO_LOG.TXT").exists()


def test_a_ctrl_c_while_the_command_exits_is_ignored(tmp_path):
    """Once the command is over (its files written, or an error said), a Ctrl-C during the
    interpreter's exit would kill the process by the signal (status -2, no message): the command
    line ignores Ctrl-C from then on, on every way out."""
    code = (
        "import signal, sys; from softgrasp.cli import main; "
        f"sys.argv = ['softgrasp', 'view', {str(tmp_path / 'missing')!r}]; status = main(); "
        "print(status, signal.getsignal(signal.SIGINT) is signal.SIG_IGN)"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env={**os.environ, "PYTHONPATH": SRC}
    )
    assert out.stdout.split() == ["2", "True"], out.stderr


def test_ctrl_c_in_plan_is_one_line(planned_sphere, tmp_path):
    # the ~4 500-node sphere plans for several seconds (the default plan may be over within 2 s)
    _assert_interrupted(_interrupt(["plan", "--mesh-size", "0.006", "--out", "p"], tmp_path, _after(2)))


_SWALLOWING_LIBRARY = """
import os, signal, sys
import softgrasp.cli.warm as warm
start = warm.warm_up_in_background

def swallowing_import():  # a library's optional import that catches every exception
    try:
        os.kill(os.getpid(), signal.SIGINT)
        signal.sigtimedwait([], 0.2)  # let the handler run here
        sum(range(10**6))
    except BaseException:
        pass
    return start()

warm.warm_up_in_background = swallowing_import
from softgrasp.cli.main import main
sys.exit(main())
"""


_FAILING_IMPORT = """
import os, signal, sys
import softgrasp.cli.warm as warm
from softgrasp.errors import ConfigError

def failing_import():  # a C extension interrupted while it initialises (NumPy's says ImportError)
    try:
        os.kill(os.getpid(), signal.SIGINT)
        signal.sigtimedwait([], 0.2)  # let the handler run here
        sum(range(10**6))
    except BaseException:
        raise {error} from None

warm.warm_up_in_background = failing_import
from softgrasp.cli.main import main
sys.exit(main())
"""


@pytest.mark.parametrize(
    "library",
    [
        _SWALLOWING_LIBRARY,
        _FAILING_IMPORT.format(error='ImportError("initialization failed")'),
        _FAILING_IMPORT.format(error='ConfigError("this needs the extra: pip install it")'),
    ],
    ids=["swallowed", "its-own-error", "softgrasp-error"],
)
def test_a_ctrl_c_a_library_swallows_or_reports_as_its_own_error_still_stops_the_plan(
    library, planned_sphere, tmp_path
):
    """A Ctrl-C caught by a library's ``except BaseException`` (trimesh's optional imports do
    this), or one that lands in a C extension's initialisation and comes out as that library's
    error (NumPy: ``ImportError: initialization failed``), which softgrasp may turn into its own
    (a missing extra), still ends the command as interrupted, 130, not 0, 2 (bad input) or 3 (an
    internal error), and leaves the earlier outputs byte-identical."""
    out = tmp_path / "p"
    out.mkdir()
    for f in ("plan.json", "object.vtu"):
        (out / f).write_bytes((planned_sphere / f).read_bytes())
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    run = subprocess.run(
        [sys.executable, "-c", library, "plan", "--out", str(out)],
        env={**os.environ, "PYTHONPATH": SRC},
        capture_output=True,
        text=True,
        timeout=240,
    )
    _assert_interrupted(run)
    assert "error" not in run.stderr
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_ctrl_c_in_calibrate_is_one_line(tmp_path):
    rows = "".join(f"{0.5 * i},{0.3 * i + 0.01 * i * i}\n" for i in range(1, 11))
    (tmp_path / "c.csv").write_text("displacement_mm,force_N\n" + rows)
    _assert_interrupted(
        _interrupt(["calibrate", "--compression", "c.csv", "--out", "c"], tmp_path, _after(4))
    )


@pytest.mark.slow
def test_ctrl_c_in_a_sweep_stops_the_workers_quietly(tmp_path):
    (tmp_path / "s.toml").write_text(
        '[base]\nobject = "sphere"\nmesh_size = 0.032\nhold_time = 0.3\n'
        "[grid]\nmu = [0.4, 0.5, 0.6, 0.7, 0.8, 0.9]\n"
    )
    results = tmp_path / "sw" / "results.csv"

    def running() -> bool:  # a case finished: the workers are up and busy
        return results.is_file() and len(results.read_text().splitlines()) >= 2

    _assert_interrupted(_interrupt(["sweep", "s.toml", "--out", "sw"], tmp_path, running))


# ----------------------------------------------------------------------- the drop's advice
def _run(reached: bool, measured: float, capped: float = 0.004, peak: float | None = None):
    """A stand-in run: both fingers read ``measured`` at the end of the closing, and ``peak`` (their
    end reading when None) at its most."""
    from types import SimpleNamespace

    peak = measured if peak is None else peak
    res = SimpleNamespace(
        reached=reached,
        fingers=("thumb", "first"),
        measured={"thumb": measured, "first": measured},
        setpoints={"thumb": 0.3, "first": 0.2},
        series={
            "phase": np.array([0, 1, 1, 1]),
            "force": np.array([[0.0] * 2, [peak] * 2, [measured] * 2, [measured] * 2]),
        },
    )
    document = {"mujoco_solver_capped_share": capped}
    return SimpleNamespace(result=res, config=ExecuteConfig(), document=document)


def test_a_closing_that_pressed_past_its_set_points_but_never_settled_is_told_apart():
    """Every finger read its set-point or more during the closing, which still did not end within
    the tolerance: the hand could press that hard; the readings jumped (a stiff object under small
    set-points), and larger set-points are the remedy, not a new plan."""
    from types import SimpleNamespace

    from softgrasp.cli.execute import _drop_advice

    args = SimpleNamespace(material=None, scale=1.0)
    advice = _drop_advice(args, _run(False, 0.1, peak=0.35))
    assert "every finger pressed as hard as its set-point" in advice and "larger set-points" in advice
    assert "could not press that hard" not in advice
    # one finger short of its set-point throughout: the hand could not press that hard
    advice = _drop_advice(args, _run(False, 0.1, peak=0.25))
    assert "could not press that hard" in advice


@pytest.mark.parametrize(
    ("reached", "measured", "material", "scale", "capped", "needle"),
    [
        (False, 0.0, None, 1.0, 0.004, "the fingers never pressed the object"),
        (
            False,
            0.1,
            None,
            1.0,
            0.004,
            "did not reach their set-points in 6 s of closing (thumb 0.1 of 0.3 N",
        ),
        (True, 0.3, "o.toml", 1.0, 0.004, "plan for it (softgrasp plan --material o.toml)"),
        (True, 0.3, None, 0.25, 0.004, "the set-points scaled by 0.25 do not hold it: raise --scale"),
        (True, 0.3, None, 1.0, 0.004, "raise the set-points (plan with --safety-factor)"),
        (False, 0.0, None, 1.0, 0.21, "constraint solver stopped at its iteration cap in 21% of the steps"),
    ],
)
def test_a_drop_is_explained_by_its_cause(reached, measured, material, scale, capped, needle):
    from types import SimpleNamespace

    from softgrasp.cli.execute import _drop_advice

    advice = _drop_advice(SimpleNamespace(material=material, scale=scale), _run(reached, measured, capped))
    assert needle in advice
    if not reached or material is not None or capped > 0.05:
        assert "raise the set-points" not in advice
