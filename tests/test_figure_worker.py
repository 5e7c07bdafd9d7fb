"""The figure worker: figures drawn by a child process are the figures drawn here, failures come
back, and a child that cannot start or dies leaves the figures to this process."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("matplotlib")

from softgrasp.viz import plots  # noqa: E402
from softgrasp.viz.worker import FigureWorker  # noqa: E402

NAMES = ["thumb", "first", "middle"]
K = np.arange(1.0, 7.0)
F = np.outer(np.linspace(0.0, 0.4, 6), [1.0, 0.7, 0.6])
P = np.outer(1e-3 * K, [1.0, 0.9, 0.8])


def _draw_all(figures: FigureWorker, out) -> None:
    figures.draw("plot_plan_forces", K, F, NAMES, out / "forces.png")
    figures.draw("plot_plan_force_penetration", P, F, NAMES, out / "force_penetration.png")


def test_the_child_draws_the_same_png_bytes_as_this_process(tmp_path):
    """Matplotlib's Agg output is deterministic: the child's files equal those drawn here."""
    here, there = tmp_path / "here", tmp_path / "there"
    plots.plot_plan_forces(K, F, NAMES, here / "forces.png")
    plots.plot_plan_force_penetration(P, F, NAMES, here / "force_penetration.png")
    with FigureWorker("child") as figures:
        assert figures.in_child
        _draw_all(figures, there)
        figures.finish()
    for name in ("forces.png", "force_penetration.png"):
        assert (there / name).read_bytes() == (here / name).read_bytes()


def test_a_worker_made_not_started_starts_its_child_when_told_or_at_its_first_figure(tmp_path):
    """``start=False``: no child until :meth:`start` (once, however often called) or the first
    figure; the figures are those drawn here."""
    plots.plot_plan_forces(K, F, NAMES, tmp_path / "here.png")
    for when in ("start", "draw"):
        with FigureWorker("child", start=False) as figures:
            assert not figures.in_child
            if when == "start":
                figures.start()
                child = figures._proc
                figures.start()
                assert figures.in_child and figures._proc is child
            figures.draw("plot_plan_forces", K, F, NAMES, tmp_path / f"{when}.png")
            assert figures.in_child
            figures.finish()
        assert (tmp_path / f"{when}.png").read_bytes() == (tmp_path / "here.png").read_bytes()


def test_a_failing_figure_raises_in_the_caller_and_the_others_are_still_drawn(tmp_path):
    """A figure whose data do not fit (three names, two force columns) raises the child's own
    error from finish(); the figure queued after it is written all the same."""
    with FigureWorker("child") as figures:
        figures.draw("plot_plan_forces", K, F[:, :2], NAMES, tmp_path / "bad.png")
        figures.draw("plot_plan_forces", K, F, NAMES, tmp_path / "good.png")
        with pytest.raises(Exception) as caught:
            figures.finish()
    with pytest.raises(type(caught.value)):
        plots.plot_plan_forces(K, F[:, :2], NAMES, tmp_path / "bad_here.png")
    assert (tmp_path / "good.png").stat().st_size > 0
    assert not (tmp_path / "bad.png").exists()
    assert not list(tmp_path.glob(".*"))  # no temporary file left behind


@pytest.mark.parametrize("why", ["refused", "inline"])
def test_figures_are_drawn_here_when_no_child_starts(tmp_path, monkeypatch, why):
    """No child where the system refuses one, or where the mode ``inline`` asks for none: the same
    files, drawn in this process."""

    def refuse(*a, **k):
        raise OSError("no processes left")

    if why == "refused":
        monkeypatch.setattr(subprocess, "Popen", refuse)
    with FigureWorker("child" if why == "refused" else "inline") as figures:
        assert not figures.in_child
        _draw_all(figures, tmp_path)
        figures.finish()
    assert (tmp_path / "forces.png").stat().st_size > 0
    assert (tmp_path / "force_penetration.png").stat().st_size > 0


@pytest.mark.parametrize("late", [False, True])
def test_figures_the_child_did_not_draw_before_it_died_are_drawn_here(tmp_path, late):
    """Jobs sent, then the child killed while it still loads Matplotlib (before it read them):
    finish() finds it dead and draws them here; so is a job queued after its death."""
    with FigureWorker("child") as figures:
        _draw_all(figures, tmp_path)
        figures._proc.kill()
        figures._proc.wait()
        if late:
            figures.draw("plot_plan_forces", K, F, NAMES, tmp_path / "late.png")
        figures.finish()
        assert not figures.in_child
    here = plots.plot_plan_forces(K, F, NAMES, tmp_path / "here.png").read_bytes()
    assert (tmp_path / "forces.png").read_bytes() == here
    assert (tmp_path / "force_penetration.png").stat().st_size > 0
    assert not late or (tmp_path / "late.png").read_bytes() == here


def test_a_failed_command_stops_an_idle_child_at_once():
    figures = FigureWorker("child")
    proc = figures._proc
    with pytest.raises(RuntimeError), figures:
        raise RuntimeError("the plan failed")
    assert proc.poll() is not None  # ended, not left running


def test_a_dead_child_does_not_end_a_caller_whose_sigpipe_is_the_default(tmp_path):
    """gmsh sets SIGPIPE back to its default action (ending the process); writing a job to a dead
    child must still only fall back to drawing here. Run in a process of its own."""
    script = f"""
import signal, sys
signal.signal(signal.SIGPIPE, signal.SIG_DFL)
import numpy as np
from pathlib import Path
from softgrasp.viz.worker import FigureWorker
with FigureWorker("child") as figures:
    figures._proc.kill()
    figures._proc.wait()
    out = Path({str(tmp_path)!r}) / "f.png"
    figures.draw("plot_plan_forces", np.arange(1.0, 4.0), np.ones((3, 3)), ["a", "b", "c"], out)
    figures.finish()
print("done")
"""
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "done"
    assert (tmp_path / "f.png").stat().st_size > 0


@pytest.mark.parametrize(("cores", "child"), [(1, False), (2, True)])
def test_auto_starts_a_child_only_with_a_second_core(monkeypatch, cores, child):
    """``auto`` follows the thread count, a fixed rule (the cores this process may use, or the
    fixed count), never the machine's momentary load."""
    from softgrasp.linalg import threads

    monkeypatch.setattr(threads, "_fixed", cores)
    with FigureWorker() as figures:
        assert figures.in_child == child


def test_an_unknown_mode_is_refused():
    with pytest.raises(ValueError, match="figure mode"):
        FigureWorker("sometimes")
