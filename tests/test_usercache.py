"""softgrasp's cache folder (:mod:`softgrasp.usercache`): built-in meshes and read hands kept
across processes, identical to what they replace, never stale, never in the way."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from softgrasp import usercache
from softgrasp.hand import urdf
from softgrasp.model import objects

SRC = str(Path(__file__).resolve().parents[1] / "src")


@pytest.fixture
def cache(tmp_path, monkeypatch):
    folder = tmp_path / "cache" / "softgrasp"
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    objects._generated.cache_clear()
    yield folder
    objects._generated.cache_clear()


def _entries(folder: Path, kind: str) -> list[Path]:
    return sorted((folder / kind).glob("*.npz")) if (folder / kind).exists() else []


@pytest.mark.parametrize("name", ["sphere", "ball:0.03", "cylinder:0.04x0.03"])
def test_a_kept_mesh_is_the_mesh_gmsh_makes(cache, name):
    made, T_made = objects._generated(name, 0.02 if name == "sphere" else None)
    assert len(_entries(cache, "meshes")) == 1
    objects._generated.cache_clear()
    kept, T_kept = objects._generated(name, 0.02 if name == "sphere" else None)
    assert np.array_equal(kept.points, made.points) and np.array_equal(kept.tets, made.tets)
    assert np.array_equal(T_kept, T_made) and kept.name == made.name
    assert not kept.points.flags.writeable  # as immutable as a generated mesh
    assert len(_entries(cache, "meshes")) == 1


def test_each_mesh_size_and_object_has_its_own_entry(cache):
    a = objects._generated("sphere", 0.02)[0]
    b = objects._generated("sphere", 0.024)[0]
    objects._generated("ball:0.03", None)
    assert a.n_nodes != b.n_nodes
    assert len(_entries(cache, "meshes")) == 3


@pytest.mark.parametrize("damage", ["not an npz file", "truncated"])
def test_a_damaged_entry_is_made_again(cache, damage):
    made = objects._generated("sphere", 0.02)[0]
    (entry,) = _entries(cache, "meshes")
    whole = entry.read_bytes()
    entry.write_bytes(b"not an npz file" if damage == "not an npz file" else whole[: len(whole) // 2])
    objects._generated.cache_clear()
    again = objects._generated("sphere", 0.02)[0]
    assert np.array_equal(again.points, made.points)
    assert entry.read_bytes() == whole  # written anew


def test_an_unwritable_cache_folder_is_no_error(tmp_path, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("a file where the cache folder would be")
    monkeypatch.setenv("XDG_CACHE_HOME", str(blocker / "cache"))
    objects._generated.cache_clear()
    try:
        assert objects._generated("ball:0.03", None)[0].n_nodes > 0
    finally:
        objects._generated.cache_clear()


def test_the_folder_follows_xdg(monkeypatch, tmp_path):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert usercache.cache_dir() == tmp_path / "softgrasp"
    monkeypatch.delenv("XDG_CACHE_HOME")
    assert usercache.cache_dir() == Path.home() / ".cache" / "softgrasp"


def test_an_entry_key_changes_with_every_part():
    base = usercache.entry_key("mesh", "sphere", 0.016, 1.0)
    assert base == usercache.entry_key("mesh", "sphere", 0.016, 1.0)
    others = (("mesh", "sphere", 0.0161, 1.0), ("mesh", "cube", 0.016, 1.0), ("mesh", "sphere", 0.016, 2.0))
    for other in others:
        assert usercache.entry_key(*other) != base


def test_a_kept_hand_is_the_hand_yourdfpy_reads(cache):
    data = (Path(urdf.__file__).parent / "shadow_like.urdf").read_bytes()
    read = urdf._read(data, "shadow_like.urdf")
    first = urdf._robot(data, "shadow_like.urdf")
    assert len(_entries(cache, "hands")) == 1
    kept = urdf._robot(data, "shadow_like.urdf")
    for got in (first, kept):
        joints, links, spheres = got
        assert links == read[1] and spheres == read[2]
        assert len(joints) == len(read[0])
        for a, b in zip(joints, read[0], strict=True):
            same = ("name", "kind", "parent", "child", "mimic", "lower", "upper", "multiplier", "offset")
            assert all(getattr(a, f) == getattr(b, f) for f in same)
            assert np.array_equal(a.origin, b.origin) and np.array_equal(a.axis, b.axis)
    chains = urdf.parse_urdf(data, "shadow_like.urdf")
    assert set(chains) == {"thumb", "first", "middle"}


def test_a_repeated_plan_neither_meshes_nor_reads_the_urdf_again(tmp_path):
    """The second default plan in a new process takes the sphere and the hand from the cache:
    gmsh and yourdfpy are not even imported, and the set-points are the same."""
    script = (
        "import sys, json; from softgrasp.cli import main; "
        "code = main(['plan', '--out', sys.argv[1]]); "
        "print(json.dumps([code, 'gmsh' in sys.modules, 'yourdfpy' in sys.modules]))"
    )
    env = {**os.environ, "PYTHONPATH": SRC, "XDG_CACHE_HOME": str(tmp_path / "cache")}
    runs = []
    for k in range(2):
        out = tmp_path / f"p{k}"
        run = subprocess.run(
            [sys.executable, "-c", script, str(out)], env=env, capture_output=True, text=True, timeout=300
        )
        assert run.returncode == 0, run.stderr
        runs.append((run.stdout.strip().splitlines()[-1], (out / "plan.json").read_text()))
    assert runs[0][0] == "[0, true, true]"
    assert runs[1][0] == "[0, false, false]"
    import json

    assert json.loads(runs[0][1])["setpoints_N"] == json.loads(runs[1][1])["setpoints_N"]


_MAKER = """
import sys, time
from softgrasp import usercache
with usercache.making("things", "k"):
    print("locked", flush=True)
    time.sleep(1.0)
    usercache.store("things", "k", {"who": "the other process"})
"""


def test_an_entry_being_made_by_another_process_is_waited_for_and_read(cache):
    """The pattern of :func:`~softgrasp.usercache.making`: while another process makes the entry
    under its lock, this one waits, finds it made and makes nothing."""
    other = subprocess.Popen(
        [sys.executable, "-c", _MAKER],
        env={**os.environ, "PYTHONPATH": SRC},
        stdout=subprocess.PIPE,
        text=True,
    )
    assert other.stdout is not None and other.stdout.readline().strip() == "locked"
    made_here = False
    kept = usercache.load("things", "k")
    assert kept is None  # not made yet: the other process holds the lock
    with usercache.making("things", "k"):
        kept = usercache.load("things", "k")
        if kept is None:
            made_here = True
    assert other.wait(60) == 0
    assert not made_here and str(kept["who"]) == "the other process"


def test_a_hand_read_meanwhile_by_another_process_is_not_read_again(cache, monkeypatch):
    """A first plan's second process reads the default hand while the first waits for it
    (:func:`softgrasp.cli.warm.warm_up_fingertips`): the waiting one does not call yourdfpy."""
    from softgrasp.hand.kinematics import HandModel

    code = (
        "import time; from softgrasp import usercache; from softgrasp.hand import urdf\n"
        "read = urdf._read\n"
        "def slow(*a):\n    print('reading', flush=True); time.sleep(1.0); return read(*a)\n"
        "urdf._read = slow\n"
        "from softgrasp.hand.kinematics import HandModel; HandModel.packaged('shadow_like')\n"
    )
    other = subprocess.Popen(
        [sys.executable, "-c", code], env={**os.environ, "PYTHONPATH": SRC}, stdout=subprocess.PIPE, text=True
    )
    assert other.stdout is not None and other.stdout.readline().strip() == "reading"

    def refuse(*_args):
        raise AssertionError("read here too")

    monkeypatch.setattr(urdf, "_read", refuse)
    hand = HandModel.packaged("shadow_like")
    assert other.wait(60) == 0
    assert hand.grasp_fingers
