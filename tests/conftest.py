"""Fixtures shared by several test modules."""

from __future__ import annotations

import math
import os
import signal

# Each pytest-xdist worker gets its share of the cores for softgrasp's threads (one each on two
# cores): two workers each running two spinning PARDISO and Numba threads on two cores nearly
# double the suite's time. Set before softgrasp is imported (``SOFTGRASP_THREADS`` is read at its
# import); a value given by the caller is kept, and tests of the thread count set it themselves.
if (workers := int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))) > 1:
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    os.environ.setdefault("SOFTGRASP_THREADS", str(max(1, cores // workers)))

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from softgrasp.offscreen import prefer_headless_gl  # noqa: E402

# MuJoCo renders offscreen in the tests as in softgrasp's commands: the back-end is chosen before
# any test module imports MuJoCo.
prefer_headless_gl()

# The Ctrl-C tests send SIGINT to softgrasp's processes. A shell without job control starts a
# background job with SIGINT ignored, its children inherit that, and Python then installs no
# handler: the commands (rightly) ignore Ctrl-C. The suite restores Python's own handler, so that
# those tests test the command line whichever way the suite was started.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.fixture
def sphere_grasp() -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Fingertip centres (thumb, first, middle) touching a 40 mm sphere on the table, the thumb
    opposite two fingers 1 rad apart, and 200 points of the sphere (an obstacle for the hand)."""
    r, n = 0.04, 200
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    phi = math.pi * (1 + 5**0.5) * k
    pts = np.column_stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z])
    normals = np.array([[math.cos(a), math.sin(a), 0.0] for a in (0.0, math.pi - 0.5, math.pi + 0.5)])
    centre = np.array([0.0, 0.0, r])
    fingers = ("thumb", "first", "middle")
    return {f: centre + (r + 0.008) * v for f, v in zip(fingers, normals, strict=True)}, centre + r * pts


@pytest.fixture
def finished_ok():
    """``finished_ok(child)``: whether a started child process ends within 60 s with exit status
    0 (one still running is killed)."""

    def check(child) -> bool:
        child.join(60)
        alive = child.is_alive()
        if alive:
            child.kill()
        return not alive and child.exitcode == 0

    return check


@pytest.fixture(scope="session")
def planned_sphere(tmp_path_factory):
    """A folder holding ``plan.json`` and ``object.vtu`` of the default sphere, planned once per
    test session by ``softgrasp plan`` (its set-points carry the default safety factor, 1.25, over
    the least that holds)."""
    from softgrasp.cli import main

    out = tmp_path_factory.mktemp("planned-sphere")
    assert main(["plan", "--out", str(out)]) == 0
    return out


def pytest_collection_modifyitems(config, items):
    """The slow tests first on every pytest-xdist worker, dealt among them in turn: started at
    once, they do not leave one worker running the last of them while another idles at the end
    of the session. (xdist's ``worksteal`` hands each of the ``n`` workers a contiguous ``1/n``
    of the collection at the start, and a worker that runs dry steals from the end of another's
    queue: with every slow test at the front of the collection, one worker ran them all.) Each
    worker's share begins with its slow tests; without xdist the slow tests simply come first."""
    n = max(1, int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")))
    slow = [item for item in items if item.get_closest_marker("slow") is not None]
    fast = [item for item in items if item.get_closest_marker("slow") is None]
    dealt = [slow[i::n] for i in range(n)]
    ordered: list = []
    for i in range(n):  # share i: its slow tests, then fast ones up to the size xdist sends it
        size = (len(items) - len(ordered)) // (n - i)
        take = max(size - len(dealt[i]), 0) if i < n - 1 else len(fast)
        ordered += dealt[i] + fast[:take]
        fast = fast[take:]
    items[:] = ordered


def pytest_sessionstart(session):
    """Note the warm servers running before the suite (:mod:`softgrasp.cli.zygote`)."""
    if not hasattr(session.config, "workerinput"):
        from softgrasp.cli import serverlock

        session.config.softgrasp_servers = {s.pid for s in serverlock.running()}


def pytest_sessionfinish(session, exitstatus):
    """Stop the warm servers the suite's ``softgrasp plan`` processes started (they would idle on
    for a quarter of an hour); the running commands of a server end first."""
    if hasattr(session.config, "workerinput"):
        return
    from softgrasp.cli import serverlock

    before = getattr(session.config, "softgrasp_servers", set())
    for s in serverlock.running():
        if s.pid not in before:
            serverlock.stop(s)
