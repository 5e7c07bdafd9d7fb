"""Output folders replaced whole: a failed, interrupted or concurrent run leaves the earlier files
byte-identical; a command removes only files its own earlier run wrote; ``--out`` is checked
before any work; sweeps resume only their own sweep file, without duplicate rows."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

import softgrasp
from softgrasp.cli import main
from softgrasp.errors import ConfigError
from softgrasp.io import runfolder
from softgrasp.io.runfolder import JOURNAL, LOCK, MANIFEST, STAGE_PREFIX, check_out, run_folder

SRC = str(Path(softgrasp.__file__).resolve().parents[1])
ENV = dict(os.environ, PYTHONPATH=SRC)
#: The cheapest plan that runs every step (coarse sphere, short hold): a few seconds.
PLAN = ["plan", "--object", "sphere", "--mesh-size", "0.032", "--hold-time", "0.3"]


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` (hidden ones included) and its bytes."""
    return {
        p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()
    }


def _write(folder, files: dict[str, str]) -> None:
    for name, text in files.items():
        p = folder.stage / name
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)


def _child(script: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(script)],
        env=ENV,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


# --- the run folder itself ---------------------------------------------------------------------


def test_a_run_replaces_its_own_files_and_removes_only_those_it_no_longer_writes(tmp_path):
    d = tmp_path / "d"
    with run_folder(d, "plan") as f:
        _write(f, {"plan.json": "1", "robust.json": "r1", "robust/samples/results.csv": "s"})
    (d / "notes.txt").write_text("mine")
    (d / "robust" / "notes.txt").write_text("mine too")
    with run_folder(d, "execute") as f:
        _write(f, {"execute.json": "e"})
    with run_folder(d, "plan") as f:
        _write(f, {"plan.json": "2"})
    assert snapshot(d).keys() == {MANIFEST, "plan.json", "notes.txt", "robust/notes.txt", "execute.json"}
    assert (d / "plan.json").read_text() == "2" and (d / "execute.json").read_text() == "e"
    assert not (d / "robust" / "samples").exists()  # the folder left empty went with its file
    owners = json.loads((d / MANIFEST).read_text())["files"]
    assert owners == {"plan.json": "plan", "execute.json": "execute"}


@pytest.mark.parametrize("failure", [RuntimeError("disk"), KeyboardInterrupt()])
def test_a_failed_or_interrupted_run_leaves_the_folder_byte_identical(tmp_path, failure):
    d = tmp_path / "d"
    with run_folder(d, "plan") as f:
        _write(f, {"plan.json": "1", "history.csv": "h1", "robust/a.csv": "a"})
    before = snapshot(d)
    with pytest.raises(type(failure)), run_folder(d, "plan") as f:
        _write(f, {"plan.json": "2", "history.csv": "h2"})
        raise failure
    assert snapshot(d) == before


def test_a_failed_first_run_leaves_no_folder(tmp_path):
    d = tmp_path / "a" / "b"
    with pytest.raises(RuntimeError), run_folder(d, "plan") as f:
        _write(f, {"plan.json": "1"})
        raise RuntimeError
    assert not (tmp_path / "a").exists()


def test_a_second_writer_is_refused_at_once(tmp_path):
    d = tmp_path / "d"
    with run_folder(d, "plan") as f:
        _write(f, {"plan.json": "1"})
    before = snapshot(d)
    # another process holds the folder (as a running softgrasp command does)
    holder = _child(
        f"""
        import sys
        from softgrasp.io.runfolder import run_folder
        with run_folder({str(d)!r}, "plan") as f:
            (f.stage / "plan.json").write_text("theirs")
            print("locked", flush=True)
            sys.stdin.readline()
        """
    )
    try:
        assert holder.stdout.readline().strip() == "locked"
        proc = subprocess.run(
            [sys.executable, "-m", "softgrasp", *PLAN, "--out", str(d)],
            env=ENV,
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert proc.returncode == 2, proc.stderr
        lines = proc.stderr.strip().splitlines()
        assert len(lines) == 1 and "another softgrasp run is writing there" in lines[0] and str(d) in lines[0]
        assert "object" not in proc.stdout  # refused before the object was even made
    finally:
        holder.communicate("\n", timeout=60)
    assert holder.returncode == 0
    assert (d / "plan.json").read_text() == "theirs"  # the holder's run, whole
    assert not (d / LOCK).exists()
    assert snapshot(d).keys() == before.keys()


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_while_computing_leaves_the_folder_as_it_was(tmp_path, sig):
    d = tmp_path / "d"
    with run_folder(d, "plan") as f:
        _write(f, {"plan.json": "1", "grasp.png": "g1"})
    before = snapshot(d)
    child = _child(
        f"""
        import sys
        from softgrasp.io.runfolder import run_folder
        with run_folder({str(d)!r}, "plan") as f:
            (f.stage / "plan.json").write_text("2")
            print("staged", flush=True)
            sys.stdin.readline()
            (f.stage / "grasp.png").write_text("g2")
        """
    )
    assert child.stdout.readline().strip() == "staged"
    child.send_signal(sig)
    child.communicate(timeout=60)
    assert child.returncode != 0
    assert snapshot(d) == before  # staging folder removed, nothing moved


def test_signals_wait_until_the_files_are_in_place(tmp_path):
    """SIGINT during the move into place is held back: every new file lands, then the run stops."""
    d = tmp_path / "d"
    child = _child(
        f"""
        import os, sys, time
        from softgrasp.io import runfolder
        real = os.replace
        def slow(src, dst):
            if str(dst).endswith("a.txt"):
                print("moving", flush=True)
                time.sleep(1.0)
            real(src, dst)
        runfolder.os.replace = slow
        with runfolder.run_folder({str(d)!r}, "plan") as f:
            for name in ("a.txt", "b.txt", "c.txt"):
                (f.stage / name).write_text(name)
        print("after", flush=True)
        """
    )
    assert child.stdout.readline().strip() == "moving"
    child.send_signal(signal.SIGINT)
    out, err = child.communicate(timeout=60)
    assert child.returncode != 0 and "KeyboardInterrupt" in err and "after" not in out
    assert {k: v.decode() for k, v in snapshot(d).items() if k != MANIFEST} == {
        n: n for n in ("a.txt", "b.txt", "c.txt")
    }


def test_a_move_cut_short_is_finished_by_the_next_run(tmp_path, monkeypatch):
    d = tmp_path / "d"
    with run_folder(d, "plan") as f:
        _write(f, {"plan.json": "1", "old.png": "o"})
    real, moved = os.replace, []

    def dies_after_one(src, dst):  # as a kill -9 in the middle of the move
        if Path(dst).name.startswith("."):  # the journal (written by a replace too)
            return real(src, dst)
        if len(moved) == 1:
            raise SystemExit("killed")
        moved.append(dst)
        real(src, dst)

    monkeypatch.setattr(runfolder.os, "replace", dies_after_one)
    monkeypatch.setattr(runfolder.shutil, "rmtree", lambda *a, **k: None)  # a killed run cleans nothing
    with pytest.raises(SystemExit), run_folder(d, "plan") as f:
        _write(f, {"history.csv": "h2", "plan.json": "2"})
    monkeypatch.undo()
    assert (d / JOURNAL).exists() and (d / "history.csv").read_text() == "h2"
    assert (d / "plan.json").read_text() == "1"  # half the set: what the journal is for
    with run_folder(d, "execute") as f:
        _write(f, {"execute.json": "e"})
    assert (d / "plan.json").read_text() == "2" and not (d / "old.png").exists()
    assert not (d / JOURNAL).exists() and not list(d.glob(STAGE_PREFIX + "*"))
    assert json.loads((d / MANIFEST).read_text())["files"] == {
        "plan.json": "plan",
        "history.csv": "plan",
        "execute.json": "execute",
    }


def test_a_damaged_manifest_removes_nothing_and_cannot_reach_outside(tmp_path):
    d = tmp_path / "d"
    d.mkdir()
    (tmp_path / "precious").write_text("x")
    (d / MANIFEST).write_text(json.dumps({"files": {"../precious": "plan"}}))
    with pytest.raises(ConfigError, match="outside its folder"), run_folder(d, "plan") as f:
        _write(f, {"plan.json": "1"})
    assert (tmp_path / "precious").read_text() == "x" and not (d / "plan.json").exists()


# --- real commands -----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def planned(tmp_path_factory) -> Path:
    """A folder written by the cheapest ``softgrasp plan``."""
    d = tmp_path_factory.mktemp("plan") / "d"
    assert main([*PLAN, "--out", str(d)]) == 0
    return d


def _copy(src: Path, dst: Path) -> Path:
    for name, data in snapshot(src).items():
        (dst / name).parent.mkdir(parents=True, exist_ok=True)
        (dst / name).write_bytes(data)
    return dst


def test_plan_keeps_a_users_file_in_a_folder_named_like_its_outputs(tmp_path, capsys):
    d = tmp_path / "d"
    (d / "robust").mkdir(parents=True)
    (d / "robust" / "notes.txt").write_text("data\n")
    (d / "robust.json").write_text("{}")  # not written by softgrasp: not softgrasp's to remove
    assert main([*PLAN, "--out", str(d)]) == 0
    assert (d / "robust" / "notes.txt").read_text() == "data\n" and (d / "robust.json").read_text() == "{}"
    assert (d / "plan.json").is_file() and (d / "grasp.png").is_file()


def test_a_plan_failing_while_writing_leaves_the_earlier_plan_byte_identical(
    planned, tmp_path, monkeypatch, capsys
):
    d = _copy(planned, tmp_path / "d")
    before = snapshot(d)
    import softgrasp.api.planning as planning

    def full_disk(*_a, **_k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(planning, "_write_frames", full_disk)  # after history.csv and the figures
    assert main(["--debug", *PLAN, "--safety-factor", "1.3", "--out", str(d)]) == 2
    err = capsys.readouterr().err
    assert "the disk is full; free space or give a folder elsewhere; its earlier files are unchanged" in err
    assert snapshot(d) == before


def test_plan_interrupted_while_planning_leaves_the_earlier_plan_byte_identical(planned, tmp_path):
    d = _copy(planned, tmp_path / "d")
    before = snapshot(d)
    for sig in (signal.SIGINT, signal.SIGTERM):
        child = subprocess.Popen(
            [sys.executable, "-m", "softgrasp", *PLAN, "--safety-factor", "1.3", "--out", str(d)],
            env=ENV,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        assert child.stdout.readline().startswith("object")  # the plan starts after this line
        child.send_signal(sig)
        child.communicate(timeout=120)
        assert child.returncode == 130
        assert snapshot(d) == before


def _robust_folder(planned: Path, d: Path) -> Path:
    """``planned`` with robust set-points of an earlier ``plan --uncertain`` (their files and
    plan.json's raised set-points, owned by plan as that run leaves them)."""
    _copy(planned, d)
    doc = json.loads((d / "plan.json").read_text())
    for f in doc["fingers"]:
        f["nominal_setpoint_N"], f["setpoint_N"] = f["setpoint_N"], 1.4 * f["setpoint_N"]
        doc["setpoints_N"][f["name"]] = f["setpoint_N"]
    doc["setpoints"] = "robust"
    (d / "plan.json").write_text(json.dumps(doc))
    (d / "robust.json").write_text('{"schema": "softgrasp.robust/1"}')
    (d / "robust" / "samples").mkdir(parents=True)
    (d / "robust" / "samples" / "results.csv").write_text("case\n0\n")
    manifest = json.loads((d / MANIFEST).read_text())
    manifest["files"].update({"robust.json": "plan", "robust/samples/results.csv": "plan"})
    (d / MANIFEST).write_text(json.dumps(manifest))
    return d


@pytest.mark.parametrize("failure", [KeyboardInterrupt, ConfigError])
def test_a_failed_robust_replan_keeps_the_earlier_robust_setpoints(planned, tmp_path, monkeypatch, failure):
    d = _robust_folder(planned, tmp_path / "d")
    before = snapshot(d)
    import softgrasp.sweep.robust as robust

    def fails(*_a, **_k):
        raise failure("cannot reach the Dask scheduler at tcp://127.0.0.1:9")

    monkeypatch.setattr(robust, "robust_setpoints", fails)
    code = main([*PLAN, "--out", str(d), "--uncertain", "mu=0.5..0.8", "--samples", "2"])
    assert code == (130 if failure is KeyboardInterrupt else 2)
    assert snapshot(d) == before
    assert json.loads((d / "plan.json").read_text())["setpoints"] == "robust"


def test_a_plan_without_robust_set_points_removes_the_earlier_ones_it_owns(planned, tmp_path):
    d = _robust_folder(planned, tmp_path / "d")
    (d / "robust" / "notes.txt").write_text("mine")
    assert main([*PLAN, "--out", str(d)]) == 0
    assert not (d / "robust.json").exists() and not (d / "robust" / "samples").exists()
    assert (d / "robust" / "notes.txt").read_text() == "mine"
    assert "robust" not in json.loads((d / "plan.json").read_text())


# --- the output folder checked at the door ------------------------------------------------------

_COMMANDS = {
    "plan": ["plan"],
    "compress": ["compress"],
    "indent": ["indent"],
    "calibrate": ["calibrate", "--compression", "missing.csv"],
    "execute": ["execute", "missing/plan.json"],
    "reproduce": ["reproduce", "--quick"],
    "sweep": ["sweep", "SWEEP"],
}


@pytest.mark.parametrize("command", sorted(_COMMANDS))
@pytest.mark.parametrize(
    ("out", "needle"),
    [
        ("", "--out is empty"),
        ("FILE", "is a file, not a folder"),
        ("FILE/sub", "is a file, so no folder can be made there"),
        ("/proc/softgrasp", "/proc is the kernel's virtual file system"),
        ("/sys/softgrasp", "/sys is the kernel's virtual file system"),
        ("x" * 300, "is longer than 255 bytes"),
    ],
)
def test_a_bad_out_is_one_line_before_any_work(tmp_path, capsys, monkeypatch, command, out, needle):
    monkeypatch.chdir(tmp_path)
    Path("FILE").write_text("a file")
    Path("SWEEP").write_text('[base]\nobject = "sphere"\n[grid]\nmu = [0.5]\n')
    import softgrasp.api.objects as objects

    def no_work(*_a, **_k):
        raise AssertionError("computed before checking --out")

    monkeypatch.setattr(objects, "load_object", no_work)
    code = main([*_COMMANDS[command], "--out", out])
    err = capsys.readouterr().err
    assert code == 2, err
    assert len(err.strip().splitlines()) == 1 and err.startswith("softgrasp: error: ") and needle in err
    assert sorted(os.listdir()) == ["FILE", "SWEEP"]


def test_view_checks_its_out_file(tmp_path, capsys, planned):
    assert main(["view", str(planned), "--out", ""]) == 2
    assert "--out is empty" in capsys.readouterr().err
    assert main(["view", str(planned), "--out", str(tmp_path)]) == 2
    assert "is a folder; give a file name" in capsys.readouterr().err


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into any folder")
def test_a_folder_that_cannot_be_written_is_refused(tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir(mode=0o555)
    with pytest.raises(ConfigError, match="is not writable"):
        check_out(ro / "d")


def test_a_file_system_error_at_the_door_is_one_line(tmp_path, monkeypatch):
    """Whatever the checks cannot foresee (a read-only mount, a full disk) is reported by the
    attempt to make the folder, before any work."""
    real = os.open

    def read_only(path, *a, **k):
        if str(path).endswith(LOCK):
            raise OSError(30, "Read-only file system")
        return real(path, *a, **k)

    monkeypatch.setattr(runfolder.os, "open", read_only)
    with pytest.raises(ConfigError, match="read-only file system; give a folder elsewhere"):
        with run_folder(tmp_path / "d", "plan"):
            raise AssertionError("ran")
    assert not (tmp_path / "d").exists()


# --- sweeps ------------------------------------------------------------------------------------


def _sweep_folder(tmp_path: Path, body: str, rows_of) -> tuple[Path, Path]:
    """A sweep file and a folder holding its results as a finished run leaves them, without
    running a case: ``rows_of(cases)`` gives the CSV rows (cells by column)."""
    from softgrasp.sweep.engine import columns
    from softgrasp.sweep.spec import describe_spec, read_sweep, spec_digest, sweep_cases

    f = tmp_path / "a.toml"
    f.write_text(body)
    spec = read_sweep(f)
    cases = sweep_cases(spec)
    d = tmp_path / "out"
    d.mkdir()
    cols = columns(spec)
    with open(d / "results.csv", "w", newline="") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(cols)
        for row in rows_of(cases):
            w.writerow([row.get(c, "") for c in cols])
    doc = {"schema": "softgrasp.sweep/1", **describe_spec(spec), "cases": len(cases)}
    (d / "sweep.json").write_text(json.dumps({**doc, "spec_sha256": spec_digest(spec)}))
    return f, d


def _row(case, **out) -> dict[str, object]:
    return {"case": case.index, "case_id": case.id, **case.options, "status": "failed", "error": "x", **out}


def test_resume_with_another_sweep_file_is_refused_and_keeps_the_rows(tmp_path, capsys):
    a = '[base]\nobject = "sphere"\n[grid]\nmu = [0.3, 0.5, 0.8]\n'
    f, d = _sweep_folder(tmp_path, a, lambda cases: [_row(c) for c in cases[:2]])
    before = snapshot(d)
    b = tmp_path / "b.toml"
    b.write_text('[base]\nobject = "sphere"\n[grid]\nmu = [0.35]\n')
    assert main(["sweep", str(b), "--out", str(d), "--resume"]) == 2
    err = capsys.readouterr().err
    assert "was made by another sweep file" in err and "a.toml" in err and len(err.splitlines()) == 1
    assert snapshot(d) == before
    # the same sweep spelled differently (another name, order, number format) is the same sweep
    same = tmp_path / "same.toml"
    same.write_text('[grid]\nmu = [0.30, 0.5, 8e-1]\n[base]\nobject = "sphere"\n')
    from softgrasp.sweep.spec import read_sweep, spec_digest

    assert spec_digest(read_sweep(same)) == spec_digest(read_sweep(f))
    assert spec_digest(read_sweep(tmp_path / "b.toml")) != spec_digest(read_sweep(f))


def test_resume_keeps_one_row_per_case(tmp_path):
    from softgrasp.sweep.engine import read_rows, run_sweep
    from softgrasp.sweep.spec import read_sweep, sweep_cases

    body = '[base]\nobject = "sphere"\n[grid]\nmu = [0.3, 0.5, 0.3]\n'  # cases 0 and 2 alike

    def rows_of(cases):  # every case finished, case 1 written twice, one row of another case 1
        other = type(cases[1])(1, "0123456789ab", cases[1].options)
        return [_row(cases[0]), _row(cases[1]), _row(cases[1]), _row(other), _row(cases[2])]

    f, d = _sweep_folder(tmp_path, body, rows_of)
    spec = read_sweep(f)
    cases = sweep_cases(spec)
    res = run_sweep(spec, cases, d, resume=True)  # nothing left to run: no cluster started
    assert res.ran == 0 and res.resumed == 3 == len(res.rows)
    assert [r["case"] for r in res.rows] == [0, 1, 2]
    assert len(read_rows(d / "results.csv", list(res.rows[0]))) == 3


def test_a_grid_over_the_case_limit_is_refused_before_any_work(tmp_path, capsys):
    values = ", ".join(str(0.1 + i * 1e-4) for i in range(1024))
    f = tmp_path / "big.toml"
    f.write_text(f"[grid]\nmu = [{values}]\nE = [{', '.join(str(1e4 + i) for i in range(1024))}]\n")
    assert main(["sweep", str(f), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "makes 1048576 cases (1024 mu x 1024 E), more than 1000000" in err
    assert not (tmp_path / "out").exists()


def test_a_sweep_with_failed_cases_exits_1_and_says_how_many(tmp_path, capsys, monkeypatch):
    from softgrasp.sweep import engine

    def rows_of(cases):
        return [_row(cases[0]), _row(cases[1], status="ok", error="")]

    body = '[base]\nobject = "sphere"\n[grid]\nmu = [0.3, 0.5]\n'
    f, d = _sweep_folder(tmp_path, body, rows_of)
    monkeypatch.setattr(engine, "_write_parquet", lambda path, cols, rows: path.write_text("parquet"))
    import softgrasp.sweep.report as report

    monkeypatch.setattr(report, "sweep_figures", lambda spec, rows, out: [])
    code = main(["sweep", str(f), "--out", str(d), "--resume"])
    captured = capsys.readouterr()
    assert code == 1
    assert "softgrasp: error: 1 of 2 cases failed" in captured.err
    assert "2 cases: 1 planned, 1 failed" in captured.out
