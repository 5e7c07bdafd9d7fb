"""Faults injected into softgrasp, as a hostile user or a failing machine would: each ends in a
clear one-line error (exit status 1 or 2, never 3, never 0), no traceback, no process left
behind, within a time bound, and an output folder holding an earlier run's files keeps them
byte-identical.

What the other tables do not cover is here: hypothesis fuzzing of the ``plan.json`` reader and
of the check that a plan's parts agree; bad inputs and mid-run failures (a full disk, an error
after the folder was locked) aimed at a folder that holds every command's earlier outputs; the
reproductions listed in the issue that asked for this suite, by name; and, in subprocesses, the
faults that need signals or several processes (two runs at once, a Ctrl-C while the Dask
cluster starts). The refusals at the door are in ``test_bad_input.py``, ``execute``'s in
``test_execute_guards.py``, the run folder's own mechanics in ``test_outputs_whole.py``.
"""

from __future__ import annotations

import copy
import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import meshio
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import softgrasp
from softgrasp.cli import main
from softgrasp.errors import SoftgraspError

SRC = str(Path(softgrasp.__file__).resolve().parents[1])
ENV = dict(os.environ, PYTHONPATH=SRC)
#: A bound against a hang (not a timing): far above what any case here takes.
BOUND_S = 120.0


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` (hidden ones included) and its bytes."""
    return {
        p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()
    }


def _run(argv: list[str], capsys) -> tuple[int, str, str]:
    """``softgrasp argv`` in this process, bounded in time: its exit status, stdout and stderr."""
    t0 = time.monotonic()
    try:
        code = main(argv)
    except SystemExit as exc:  # the argument parser's refusals
        code = int(exc.code or 0)
    assert time.monotonic() - t0 < BOUND_S, f"softgrasp {argv} took more than {BOUND_S} s"
    cap = capsys.readouterr()
    return code, cap.out, cap.err


def assert_clear_error(code: int, err: str, needle: str = "") -> None:
    """Exit status 1 or 2, exactly one line on stderr starting 'softgrasp: ', no traceback."""
    lines = err.strip().splitlines()
    assert code in (1, 2), (code, err)
    assert len(lines) == 1, err
    assert lines[0].startswith("softgrasp: ") and "internal error" not in lines[0], err
    assert "Traceback" not in err
    assert needle in lines[0], err


# =============================================================================== plan.json fuzzing
#: Bounded, reproducible fuzzing: the same examples on every run, no example database on disk.
FUZZ = settings(
    max_examples=120,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)

_json = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(min_value=-(2**70), max_value=2**70)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.sampled_from([0.0, -1.0, 1e300, -1e300, 1e-300, "", "thumb", "sha256:" + "0" * 64, "object.vtu"])
    | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=4),
    max_leaves=8,
)


def _paths(node: object, prefix: tuple = ()) -> list[tuple]:
    """The path of every node of a JSON document (keys and list indices)."""
    out = [prefix]
    if isinstance(node, dict):
        for k, v in node.items():
            out += _paths(v, (*prefix, k))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            out += _paths(v, (*prefix, i))
    return out


def _edit(doc: dict, path: tuple, op: str, value: object) -> dict:
    """``doc`` with the node at ``path`` deleted, replaced, scaled, or (a list) cut, grown or
    reordered."""
    if not path:
        return value if op == "replace" else doc  # type: ignore[return-value]
    parent = doc
    for key in path[:-1]:
        parent = parent[key]
    key, node = path[-1], parent[path[-1]]
    if op == "delete":
        del parent[key]
    elif op == "replace":
        parent[key] = value
    elif op == "scale" and isinstance(node, int | float) and not isinstance(node, bool):
        parent[key] = node * (value if isinstance(value, int | float) else 1e300)
    elif op == "cut" and isinstance(node, list):
        del node[len(node) // 2 :]
    elif op == "grow" and isinstance(node, list):
        node.append(copy.deepcopy(node[-1]) if node else value)
    elif op == "reverse" and isinstance(node, list):
        node.reverse()
    return doc


@pytest.fixture(scope="module")
def plan_doc(planned_sphere) -> dict:
    return json.loads((planned_sphere / "plan.json").read_text())


def _read_plan(folder: Path, text: str, planned: Path) -> None:
    """Write ``text`` as plan.json beside the planned mesh and read it as ``execute`` and
    ``plan --grasp`` do: a valid plan or a SoftgraspError, never another exception."""
    from softgrasp.execution.plan_check import check_plan
    from softgrasp.io.limits import PLAN_RANGES
    from softgrasp.io.planfile import load_plan_file, load_plan_grasp

    path = folder / "plan.json"
    path.write_text(text)
    if not (folder / "object.vtu").exists():
        shutil.copyfile(planned / "object.vtu", folder / "object.vtu")
    try:
        plan = load_plan_file(path)
    except SoftgraspError:
        pass
    else:
        for name, value in (("object.mass_kg", plan.mass), ("object.material.E_Pa", plan.E)):
            assert PLAN_RANGES[name].contains(value), (name, value)
        assert len({f.name for f in plan.fingers}) == len(plan.fingers) and plan.palm_pose.shape == (4, 4)
        try:
            hand, mesh = check_plan(plan)
        except SoftgraspError:
            pass
        else:
            assert {f.name for f in plan.fingers} <= set(hand.fingers) and mesh.n_tets > 0
    try:
        grasp = load_plan_grasp(path)
    except SoftgraspError:
        return
    assert grasp.points.shape == (3, 3) and np.isfinite(grasp.points).all()


@FUZZ
@given(
    edits=st.lists(
        st.tuples(
            st.integers(min_value=0, max_value=10**6),
            st.sampled_from(["delete", "replace", "replace", "scale", "cut", "grow", "reverse"]),
            _json,
        ),
        min_size=1,
        max_size=3,
    )
)
def test_an_edited_plan_file_is_read_or_refused(edits, plan_doc, planned_sphere, tmp_path_factory) -> None:
    """Random deletions, replacements (any JSON value), scalings and list edits of a real
    plan.json's fields: load_plan_file and check_plan return a valid plan or raise a
    SoftgraspError."""
    doc = copy.deepcopy(plan_doc)
    for pick, op, value in edits:
        paths = _paths(doc) if isinstance(doc, dict) else [()]
        doc = _edit(doc, paths[pick % len(paths)], op, value)
        if not isinstance(doc, dict):
            break
    _read_plan(tmp_path_factory.mktemp("plan"), json.dumps(doc), planned_sphere)


@FUZZ
@given(doc=_json, schema=st.booleans())
def test_any_json_document_as_a_plan_file_is_refused(doc, schema, planned_sphere, tmp_path_factory) -> None:
    if schema and isinstance(doc, dict):
        doc["schema"] = "softgrasp.plan/2"
    _read_plan(tmp_path_factory.mktemp("plan"), json.dumps(doc), planned_sphere)


@settings(FUZZ, max_examples=60)
@given(raw=st.binary(max_size=300), cut=st.integers(min_value=0, max_value=20_000))
def test_a_damaged_plan_file_is_refused(raw, cut, plan_doc, planned_sphere, tmp_path_factory) -> None:
    """Raw bytes, and the real file cut short or with bytes spliced in."""
    text = json.dumps(plan_doc)
    folder = tmp_path_factory.mktemp("plan")
    (folder / "plan.json").write_bytes(raw)
    _read_plan_bytes(folder, planned_sphere)
    (folder / "plan.json").write_bytes(text[: cut % len(text)].encode() + raw)
    _read_plan_bytes(folder, planned_sphere)


def _read_plan_bytes(folder: Path, planned: Path) -> None:
    from softgrasp.io.planfile import load_plan_file

    shutil.copyfile(planned / "object.vtu", folder / "object.vtu")
    with pytest.raises(SoftgraspError):
        load_plan_file(folder / "plan.json")


# ============================================== bad inputs into a folder of earlier outputs
#: The cheapest plan that runs every step (coarse sphere, short hold).
PLAN = ["plan", "--object", "sphere", "--mesh-size", "0.032", "--hold-time", "0.3"]
#: Earlier outputs of the commands other than plan, as their runs leave them (manifest included).
EARLIER = {
    "compress": {"compress.json": '{"schema": "softgrasp.compress/1"}\n', "compress.csv": "strain\n0.1\n"},
    "indent": {"indent.json": '{"schema": "softgrasp.indent/1"}\n', "indent.png": "png"},
    "calibrate": {"calibration.json": "{}\n", "material.toml": "[material]\nE_Pa = 1e5\nnu = 0.45\n"},
    "execute": {"execute.json": '{"held": true}\n', "execute.csv": "t\n0\n"},
    "reproduce": {"report.md": "# report\n"},
}


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> Path:
    """Bad input files the cases name (``{i}/NAME``)."""
    d = tmp_path_factory.mktemp("inputs")
    p = 0.02 * np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [-1, 0, 0], [0, -1, 0], [0, 0, -1]])
    meshio.write(d / "vertex.vtu", meshio.Mesh(p, [("tetra", np.array([[0, 1, 2, 3], [0, 4, 6, 5]]))]))
    (d / "config.toml").write_text('mesh_size = "abc"\n')
    (d / "sweep_bad.toml").write_text("[grid]\nmu = [0.5, 1e300]\n")
    (d / "sweep_other.toml").write_text('[base]\nobject = "sphere"\n[grid]\nmu = [0.35]\n')
    (d / "text.csv").write_text("this is not a table\n")
    (d / "one_row.csv").write_text("displacement_mm,force_N\n0.5,0.1\n")
    (d / "nan.csv").write_text("displacement_mm,force_N\n0.5,nan\n1.0,0.2\n1.5,0.3\n")
    (d / "negative.csv").write_text("displacement_mm,force_N\n0.5,-0.1\n1.0,-0.2\n1.5,-0.3\n")
    rows = "".join(f"{0.5 * i},{0.1 * i + 0.01 * i * i}\n" for i in range(1, 9))
    (d / "curve.csv").write_text("displacement_mm,force_N\n" + rows)  # a valid compression curve
    (d / "not_json.json").write_text("{plan")
    (d / "stone.toml").write_text('[material]\nname = "stone"\nE_Pa = 1e300\nnu = 0.3\n')
    (d / "hand.urdf").write_text("<robot name='x'><link name='a'/></robot>")
    return d


@pytest.fixture(scope="module")
def earlier(planned_sphere, tmp_path_factory) -> Path:
    """A folder holding every command's earlier outputs (the plan's real ones), a sweep's results
    and a user's own files."""
    from softgrasp.io.runfolder import run_folder

    d = tmp_path_factory.mktemp("earlier") / "d"
    shutil.copytree(planned_sphere, d)
    for owner, files in EARLIER.items():
        with run_folder(d, owner) as f:
            for name, text in files.items():
                (f.stage / name).write_text(text)
    with run_folder(d, "sweep") as f:
        (f.stage / "results.csv").write_text("case,case_id,mu,status\n0,abc,0.3,ok\n")
        (f.stage / "sweep.json").write_text('{"schema": "softgrasp.sweep/1", "spec_sha256": "sha256:0"}\n')
    (d / "notes.txt").write_text("mine\n")
    (d / "robust").mkdir()
    (d / "robust" / "notes.txt").write_text("mine too\n")
    return d


def _folder_case(args: list[str], needle: str) -> object:
    return pytest.param(args, needle, id=" ".join(a.replace("{i}/", "") for a in args))


FOLDER_CASES = [
    # plan: at the door, and after the folder is locked (object, material, grasp, hand, ranges)
    _folder_case(["plan", "--mu", "1e300"], "--mu must be a number in [0, 5]"),
    _folder_case(["plan", "--config", "{i}/config.toml"], "mesh_size must be a number"),
    _folder_case(["plan", "--object", "teapot"], "unknown object 'teapot'"),
    _folder_case(["plan", "--object", "{i}/vertex.vtu"], "falls apart into 2 parts"),
    _folder_case(["plan", "--material", "granite"], "unknown material 'granite'"),
    _folder_case(["plan", "--material", "{i}/stone.toml"], "E = 1e+300 Pa is invalid"),
    _folder_case(["plan", "--grasp", "{i}/missing.json"], "does not exist"),
    _folder_case(["plan", "--grasp", "{i}/not_json.json"], "is not readable JSON"),
    _folder_case(["plan", "--hand", "{i}/missing.urdf"], "missing.urdf"),
    _folder_case(["plan", "--hand", "{i}/hand.urdf"], "hand.urdf"),
    _folder_case(["plan", "--samples", "8"], "--samples applies to robust set-points"),
    _folder_case(["plan", "--uncertain", "mu=0.9..0.1"], "mu"),
    _folder_case(["plan", "--uncertain", "colour=1..2"], "colour"),
    _folder_case(["plan", "--uncertain", "mu=0.4..0.8", "--uncertain", "mu=0.5..0.6"], "mu"),
    # the material experiments
    _folder_case(["compress", "--object", "box:1e300x1e300x1e300"], "measures 1e+300"),
    _folder_case(["compress", "--material", "E=1,nu=0.3,density=50"], "E = 1 Pa is invalid"),
    _folder_case(["compress", "--object", "{i}/vertex.vtu"], "falls apart into 2 parts"),
    _folder_case(["indent", "--depth", "inf"], "--depth must be a number"),
    _folder_case(["indent", "--object", "ball:1e6"], "1 mm to 0.5 m"),
    _folder_case(["indent", "--object", "box:0.004", "--density", "1000", "--depth", "0.009"], "depth"),
    _folder_case(["calibrate", "--compression", "{i}/missing.csv"], "missing.csv"),
    _folder_case(["calibrate", "--compression", "{i}/text.csv"], "text.csv"),
    _folder_case(["calibrate", "--compression", "{i}/one_row.csv"], "one_row.csv"),
    _folder_case(["calibrate", "--compression", "{i}/nan.csv"], "nan.csv"),
    _folder_case(["calibrate", "--compression", "{i}/negative.csv"], "negative.csv"),
    _folder_case(["calibrate", "--compression", "{i}/one_row.csv", "--steps", "0"], "--steps"),
    # execute: its plan, options and material file
    _folder_case(["execute", "{i}/missing/plan.json"], "does not exist"),
    _folder_case(["execute", "{i}/not_json.json"], "is not readable JSON"),
    _folder_case(["execute", "{p}/plan.json", "--lift", "1e300"], "--lift = 1e+300 m is not physical"),
    _folder_case(["execute", "{p}/plan.json", "--scale", "1e300"], "--scale = 1e+300 is not physical"),
    _folder_case(["execute", "{p}/plan.json", "--material", "{i}/stone.toml"], "E = 1e+300 Pa"),
    # sweeps: a bad file, another sweep's results with and without --resume, too many cases
    _folder_case(["sweep", "{i}/sweep_bad.toml"], "mu"),
    _folder_case(["sweep", "{i}/sweep_other.toml"], "results.csv exists: add --resume"),
    _folder_case(["sweep", "{i}/sweep_other.toml", "--resume"], "was made by another sweep file"),
    _folder_case(["sweep", "{i}/sweep_other.toml", "--workers", "0"], "--workers"),
]


def _argv(args: list[str], inputs: Path, planned: Path, out: Path) -> list[str]:
    return [a.replace("{i}", str(inputs)).replace("{p}", str(planned)) for a in args] + ["--out", str(out)]


@pytest.mark.parametrize(("args", "needle"), FOLDER_CASES)
def test_bad_input_leaves_a_folder_of_earlier_outputs_byte_identical(
    args, needle, inputs, earlier, planned_sphere, tmp_path, capsys
):
    d = tmp_path / "d"
    shutil.copytree(earlier, d)
    before = snapshot(d)
    code, _, err = _run(_argv(args, inputs, planned_sphere, d), capsys)
    assert_clear_error(code, err, needle)
    assert snapshot(d) == before  # no file changed, added (lock, staging folder) or removed


# ================================================================ failures while a run works
class _FullDisk:
    """The ``tempfile`` module as :mod:`softgrasp.io.atomic` sees it on a full disk: every new
    file fails with ENOSPC."""

    def __getattr__(self, name: str) -> object:
        import tempfile

        return getattr(tempfile, name)

    @staticmethod
    def mkstemp(*_a, **_k):
        raise OSError(errno.ENOSPC, "No space left on device")


def _fail(exc: BaseException):
    def fails(*_a, **_k):
        raise exc

    return fails


def _inject(monkeypatch, fault: str) -> None:
    import softgrasp.api.calibration as calibration
    import softgrasp.api.planning as planning
    import softgrasp.io.atomic as atomic
    import softgrasp.io.runfolder as runfolder
    from softgrasp.errors import NotConverged, SimulationUnstable
    from softgrasp.execution.mujoco.hand import MujocoHand

    if fault == "full disk":
        monkeypatch.setattr(atomic, "tempfile", _FullDisk())
    elif fault == "full disk at the move":
        monkeypatch.setattr(runfolder, "write_json", _fail(OSError(errno.ENOSPC, "No space left on device")))
    elif fault == "plan not converged":
        monkeypatch.setattr(planning, "plan", _fail(NotConverged("the static solve did not converge")))
    elif fault == "calibration not converged":
        monkeypatch.setattr(calibration, "calibrate", _fail(NotConverged("the fit did not converge")))
    elif fault == "MuJoCo blow-up":
        monkeypatch.setattr(
            MujocoHand, "step", _fail(SimulationUnstable("MuJoCo's simulation became unstable"))
        )


QUICK_COMPRESS = ["compress", "--object", "box:0.04", "--density", "1000", "--strain", "0.02", "--steps", "2"]
QUICK_INDENT = ["indent", "--object", "box:0.04", "--density", "1000", "--depth", "0.001", "--steps", "5"]


def _midway(args: list[str], fault: str, needle: str, *marks) -> object:
    return pytest.param(args, fault, needle, marks=marks, id=f"{args[0]}: {fault}")


@pytest.mark.parametrize(
    ("args", "fault", "needle"),
    [
        _midway(
            QUICK_COMPRESS,
            "full disk",
            "the disk is full; free space or give a folder elsewhere; its earlier",
        ),
        _midway(QUICK_INDENT, "full disk", "the disk is full"),
        _midway(QUICK_COMPRESS, "full disk at the move", "the disk is full"),
        _midway(["plan"], "plan not converged", "the static solve did not converge"),
        _midway(
            ["calibrate", "--compression", "{i}/curve.csv"], "calibration not converged", "did not converge"
        ),
        _midway(["execute", "{p}/plan.json"], "MuJoCo blow-up", "became unstable"),
        _midway(["execute", "{p}/plan.json"], "full disk", "the disk is full", pytest.mark.slow),
    ],
)
def test_a_run_failing_midway_leaves_the_earlier_outputs_byte_identical(
    args, fault, needle, inputs, earlier, planned_sphere, tmp_path, capsys, monkeypatch
):
    d = tmp_path / "d"
    shutil.copytree(earlier, d)
    before = snapshot(d)
    _inject(monkeypatch, fault)
    code, _, err = _run(_argv(args, inputs, planned_sphere, d), capsys)
    assert_clear_error(code, err, needle)
    assert snapshot(d) == before


# ======================================================== faults that need processes and signals
def _group_left(pid: int) -> list[str]:
    """The processes of the group ``pid`` still alive (exited children are reaped by init)."""
    left: list[str] = []
    for _ in range(50):
        found = subprocess.run(["pgrep", "-g", str(pid)], capture_output=True, text=True).stdout.split()
        left = [p for p in found if not _zombie(p)]
        if not left:
            break
        time.sleep(0.2)
    return left


def _zombie(pid: str) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    except (OSError, IndexError):
        return True


def _child(cmd: list[str], *, cwd: Path, sig: int | None = None, after: float = 0.0) -> tuple[int, str, str]:
    """Run ``cmd`` in its own process group (a terminal's job), send the group ``sig`` ``after``
    seconds, and return how it ended; fail if it outlives the bound or leaves a process behind."""
    p = subprocess.Popen(
        cmd,
        cwd=cwd,
        env=ENV,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        if sig is not None:
            try:
                p.wait(after)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, sig)
            else:
                raise AssertionError("the command ended before it could be interrupted")
        out, err = p.communicate(timeout=BOUND_S)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.communicate()
    assert not _group_left(p.pid), "processes left behind"
    return p.returncode, out, err


def _assert_interrupted(code: int, err: str) -> None:
    assert code == 130, err
    assert err.strip().splitlines() == ["softgrasp: interrupted"], err


_CLUSTER_START_INTERRUPTED = """
import os, signal, sys, time
from softgrasp.sweep import engine
start = engine._start_client

def interrupted_start(scheduler, workers):
    client, cluster = start(scheduler, workers)  # the workers are up, the start not yet over
    os.killpg(0, signal.SIGINT)  # a Ctrl-C at the terminal reaches every process of the job
    time.sleep(0.5)
    return client, cluster

engine._start_client = interrupted_start
from softgrasp.cli import main
sys.exit(main(sys.argv[1:]))
"""


def test_a_ctrl_c_while_the_dask_cluster_starts_stops_the_sweep(earlier, tmp_path):
    """Pressed while the workers start (their SIGINT is blocked, not ignored by this process), the
    Ctrl-C is acted on once the start is over: the cluster closed, no case run, exit 130."""
    d = tmp_path / "d"
    shutil.copytree(earlier, d)
    (d / "results.csv").unlink()  # the folder of an earlier plan, not of an earlier sweep
    before = snapshot(d)
    (tmp_path / "s.toml").write_text('[base]\nobject = "sphere"\nmesh_size = 0.032\n[grid]\nmu = [0.5]\n')
    cmd = [sys.executable, "-c", _CLUSTER_START_INTERRUPTED, "sweep", "s.toml", "--out", str(d)]
    code, out, err = _child(cmd, cwd=tmp_path)
    _assert_interrupted(code, err)
    assert "cases:" not in out  # no case ran
    assert snapshot(d) == before


@pytest.mark.parametrize(
    ("args", "sig"),
    [
        (["execute", "{p}/plan.json"], signal.SIGINT),
        (["execute", "{p}/plan.json"], signal.SIGTERM),
        (["calibrate", "--compression", "{i}/curve.csv"], signal.SIGINT),
    ],
    ids=["execute SIGINT", "execute SIGTERM", "calibrate SIGINT"],
)
def test_an_interrupted_run_leaves_the_earlier_outputs_byte_identical(
    args, sig, inputs, earlier, planned_sphere, tmp_path
):
    d = tmp_path / "d"
    shutil.copytree(earlier, d)
    before = snapshot(d)
    cmd = [sys.executable, "-m", "softgrasp", *_argv(args, inputs, planned_sphere, d)]
    code, _, err = _child(cmd, cwd=tmp_path, sig=sig, after=5.0)
    _assert_interrupted(code, err)
    assert snapshot(d) == before


@pytest.mark.slow
def test_two_plans_at_once_one_writes_the_other_is_refused(earlier, tmp_path):
    d = tmp_path / "d"
    shutil.copytree(earlier, d)
    before = snapshot(d)
    runs = [
        subprocess.Popen(
            [sys.executable, "-m", "softgrasp", *PLAN, "--safety-factor", f, "--out", str(d)],
            env=ENV,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for f in ("1.3", "1.4")
    ]
    ends = [(p.communicate(timeout=BOUND_S), p.returncode) for p in runs]
    codes = sorted(code for _, code in ends)
    assert codes == [0, 2], ends
    (_, lost_err), _ = next(e for e in ends if e[1] == 2)
    assert_clear_error(2, lost_err, "another softgrasp run is writing there")
    winner = runs[[code for _, code in ends].index(0)].args[-3]
    after = snapshot(d)
    plan_files = {  # the plan's files before and after (the winner removes the stale ones)
        name
        for snap in (before, after)
        for name, owner in json.loads(snap[".softgrasp-manifest.json"])["files"].items()
        if owner == "plan"
    }
    assert json.loads(after["plan.json"])["margin"]["safety_factor"] == float(winner)
    assert {k: v for k, v in after.items() if k not in plan_files and not k.startswith(".")} == {
        k: v for k, v in before.items() if k not in plan_files and not k.startswith(".")
    }
    assert not [n for n in after if n.startswith(".softgrasp-stage") or "/.softgrasp-stage" in n]


# ====================================================== the reproductions listed in the issue
def _tamper(doc: dict, how: str) -> None:
    f = doc["fingers"]
    if how == "duplicated finger":
        f[1] = copy.deepcopy(f[0])
    elif how == "fourth finger":
        f.append({**copy.deepcopy(f[0]), "name": "ring"})
    elif how == "swapped fingers":
        f[0]["name"], f[1]["name"] = f[1]["name"], f[0]["name"]
    elif how == "palm 1e6 m away":
        doc["hand"]["palm_pose"][0][3] += 1e6
    elif how == "E_Pa 1e300":
        doc["object"]["material"]["E_Pa"] = 1e300
    elif how == "mu 1e300":
        doc["parameters"]["contact"]["mu"] = 1e300


@pytest.fixture(scope="module")
def issue_files(planned_sphere, plan_doc, tmp_path_factory) -> Path:
    """The files of the issue's reproductions (``{r}/NAME``)."""
    from softgrasp.model.mesh.generate import sphere
    from softgrasp.model.mesh.io import load_mesh, save_mesh
    from softgrasp.model.mesh.tetmesh import TetMesh

    d = tmp_path_factory.mktemp("issue")
    for how in (
        "duplicated finger",
        "fourth finger",
        "swapped fingers",
        "palm 1e6 m away",
        "E_Pa 1e300",
        "mu 1e300",
    ):
        doc = copy.deepcopy(plan_doc)
        _tamper(doc, how)
        sub = d / how.replace(" ", "_")
        sub.mkdir()
        (sub / "plan.json").write_text(json.dumps(doc))
        shutil.copyfile(planned_sphere / "object.vtu", sub / "object.vtu")
    other = d / "other_object"
    other.mkdir()
    shutil.copyfile(planned_sphere / "plan.json", other / "plan.json")
    mesh = load_mesh(planned_sphere / "object.vtu")
    save_mesh(TetMesh(mesh.points * np.array([1.0, 1.0, 1.01]), mesh.tets), other / "object.vtu")
    for name, text in (
        ("size", 'mesh_size = "abc"'),
        ("int", "material = 5"),
        ("list", 'material = ["rubber"]'),
    ):
        (d / f"{name}.toml").write_text(text + "\n")
    p = 0.02 * np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [-1, 0, 0], [0, -1, 0], [0, 0, -1]])
    meshio.write(d / "vertex.vtu", meshio.Mesh(p, [("tetra", np.array([[0, 1, 2, 3], [0, 4, 6, 5]]))]))
    ball = sphere(0.02, 0.01)
    pts = np.vstack([ball.points, ball.points + [0.1, 0.0, 0.0]])
    meshio.write(
        d / "two_balls.vtu", meshio.Mesh(pts, [("tetra", np.vstack([ball.tets, ball.tets + ball.n_nodes]))])
    )
    hexa = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]])
    cells = [("tetra", ball.tets), ("hexahedron", np.arange(8)[None] + ball.n_nodes)]
    meshio.write(d / "mixed.vtu", meshio.Mesh(np.vstack([ball.points, 0.01 * hexa + [0.03, 0, 0]]), cells))
    values = ", ".join(str(0.1 + i * 1e-4) for i in range(1024))
    (d / "grid.toml").write_text(
        f"[grid]\nmu = [{values}]\nE = [{', '.join(str(1e4 + i) for i in range(1024))}]\n"
    )
    (d / "a_file").write_text("a file\n")
    return d


def _issue(name: str, args: list[str], needle: str) -> object:
    return pytest.param(args, needle, id=name)


ISSUE = [
    _issue("execute --lift 1e300 (ran for 300 s)", ["execute", "{p}/plan.json", "--lift", "1e300"], "--lift"),
    _issue("plan.json E_Pa 1e300 (MuJoCo QACC warnings)", ["execute", "{r}/E_Pa_1e300/plan.json"], "E_Pa"),
    _issue("plan.json mu 1e300 (MuJoCo QACC warnings)", ["execute", "{r}/mu_1e300/plan.json"], "contact.mu"),
    _issue("1048576-case grid sweep", ["sweep", "{r}/grid.toml"], "more than 1000000"),
    _issue("--out an existing file", ["plan", "--out", "{r}/a_file"], "is a file, not a folder"),
    _issue("--out under /proc", ["execute", "{p}/plan.json", "--out", "/proc/sg"], "virtual file system"),
    _issue(
        "--out under /sys", ["calibrate", "--compression", "c.csv", "--out", "/sys/sg"], "virtual file system"
    ),
    _issue("--out name too long", ["plan", "--out", "x" * 300], "longer than 255 bytes"),
    _issue("--out ''", ["compress", "--out", ""], "--out is empty"),
    _issue("mesh_size = 'abc'", ["plan", "--config", "{r}/size.toml"], "mesh_size must be a number"),
    _issue("material = 5", ["plan", "--config", "{r}/int.toml"], "material must be text"),
    _issue("material = ['rubber']", ["plan", "--config", "{r}/list.toml"], "material must be text"),
    _issue("--object box:1e300x1e300x1e300", ["plan", "--object", "box:1e300x1e300x1e300"], "1 mm to 0.5 m"),
    _issue(
        "--hold-time 1e300", ["plan", "--hold-time", "1e300"], "--hold-time must be a number in (0, 60] s"
    ),
    _issue("indent --depth inf", ["indent", "--depth", "inf"], "--depth must be a number"),
    _issue(
        "--scheduler not-a-url", ["sweep", "{r}/grid.toml", "--scheduler", "not-a-url"], "tcp://HOST:PORT"
    ),
    _issue("two tets touching at a vertex", ["compress", "--object", "{r}/vertex.vtu"], "falls apart"),
    _issue("plan.json duplicated finger", ["execute", "{r}/duplicated_finger/plan.json"], "appears twice"),
    _issue("plan.json fourth finger", ["execute", "{r}/fourth_finger/plan.json"], "'ring' is not a finger"),
    _issue(
        "--mu 1e300 (said: raise the friction)", ["plan", "--mu", "1e300"], "--mu must be a number in [0, 5]"
    ),
    _issue("--safety-factor 1000 (said: 0.00 N)", ["plan", "--safety-factor", "1000"], "in [1, 20]"),
    _issue(
        "weightless object (said: a lighter object)",
        ["plan", "--material", "E=1e5,nu=0.3,density=0.01"],
        "density = 0.01 kg/m^3 is invalid",
    ),
    _issue(
        "calibrate --steps 0 (said: check the mesh)",
        ["calibrate", "--compression", "c.csv", "--steps", "0"],
        "--steps",
    ),
    _issue("execute swapped fingers", ["execute", "{r}/swapped_fingers/plan.json"], "fingers swapped?"),
    _issue("execute another object.vtu", ["execute", "{r}/other_object/plan.json"], "is not the one planned"),
    _issue(
        "execute palm 1e6 m away", ["execute", "{r}/palm_1e6_m_away/plan.json"], "the palm pose was moved"
    ),
    _issue("1e-9 m object compressed", ["compress", "--object", "box:1e-9"], "1 mm to 0.5 m"),
    _issue("1e6 m object indented", ["indent", "--object", "ball:1e6"], "1 mm to 0.5 m"),
    _issue(
        "two tet spheres in one VTU", ["indent", "--object", "{r}/two_balls.vtu"], "falls apart into 2 parts"
    ),
    _issue("hexahedra in a mixed mesh", ["compress", "--object", "{r}/mixed.vtu"], "1 hexahedron"),
    _issue("execute --scale 1e300 (exited 0)", ["execute", "{p}/plan.json", "--scale", "1e300"], "--scale"),
]


@pytest.mark.parametrize(("args", "needle"), ISSUE)
def test_the_issues_reproductions_are_clear_errors(
    args, needle, issue_files, planned_sphere, tmp_path, capsys
):
    argv = [a.replace("{r}", str(issue_files)).replace("{p}", str(planned_sphere)) for a in args]
    if "--out" not in argv:
        argv += ["--out", str(tmp_path / "out")]
    code, _, err = _run(argv, capsys)
    assert_clear_error(code, err, needle)
    assert not (tmp_path / "out").exists()


def _closed_port() -> int:
    """A TCP port on the loopback interface where nothing listens."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("command", ["plan", "sweep"])
def test_an_unreachable_scheduler_is_refused_before_any_work(
    command, inputs, earlier, tmp_path, capsys, monkeypatch
):
    """(The issue: a robust re-plan with an unreachable --scheduler replaced the robust
    set-points; it then waited 20 s for the scheduler after planning.)"""
    import softgrasp.api.planning as planning

    monkeypatch.setattr(planning, "plan", _fail(AssertionError("planned before checking --scheduler")))
    d = tmp_path / "d"
    shutil.copytree(earlier, d)
    (d / "results.csv").unlink()
    before = snapshot(d)
    address = f"tcp://127.0.0.1:{_closed_port()}"
    (tmp_path / "s.toml").write_text('[base]\nobject = "sphere"\n[grid]\nmu = [0.5]\n')
    args = {
        "plan": ["plan", "--mesh-size", "0.032", "--uncertain", "mu=0.5..0.8", "--samples", "4"],
        "sweep": ["sweep", str(tmp_path / "s.toml")],
    }[command]
    code, _, err = _run([*args, "--scheduler", address, "--out", str(d)], capsys)
    assert_clear_error(code, err, f"cannot reach the Dask scheduler at {address}: connection refused")
    assert snapshot(d) == before


def test_an_interrupted_command_run_in_process_leaves_ctrl_c_to_its_caller(tmp_path, capsys, monkeypatch):
    """``main(argv)`` called by a program (or a test) that is interrupted returns 130 and leaves
    the caller's SIGINT handler in place: later Ctrl-Cs, and the processes it starts, see it."""
    import softgrasp.api.objects as objects

    monkeypatch.setattr(objects, "load_object", _fail(KeyboardInterrupt()))
    before = signal.getsignal(signal.SIGINT)
    code, _, err = _run(["compress", "--out", str(tmp_path / "c")], capsys)
    _assert_interrupted(code, err)
    assert signal.getsignal(signal.SIGINT) is before
