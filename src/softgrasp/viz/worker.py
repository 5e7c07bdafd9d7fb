"""Figures drawn by a child process while the caller computes.

Importing Matplotlib, loading its fonts and drawing the figures of ``softgrasp plan`` take about
as long as planning the default object. A :class:`FigureWorker` started before the work begins
loads Matplotlib on the other core meanwhile; the figures the caller then hands it
(:meth:`FigureWorker.draw`) are drawn there while the caller writes its other files.
:meth:`FigureWorker.finish` waits for them and raises the first failure as drawing in this
process would have.

The child is this module run by the same interpreter (``python -m softgrasp.viz.worker``): it
does not depend on how the caller was started, nor on the threads the caller runs. Jobs and
answers go as pickles through a socket that is the child's standard input and output; the caller
writes with ``MSG_NOSIGNAL``, so a dead child is an error it handles, never a SIGPIPE that would
end it (gmsh, which meshes the object first, sets SIGPIPE back to its default action). Where no
child can be started, or it dies, the figures not yet drawn are drawn here: the same files, only
later. Each figure function writes its PNG atomically, so a failure or a stopped child leaves no
half-written file.

``FigureWorker(mode, start=False)`` starts the child later, when the caller calls :meth:`~FigureWorker.start`
or at the first figure (a first run of ``softgrasp plan`` starts it once its kernels are
compiled, so that Matplotlib's start does not take CPU from the compiling).
``FigureWorker(mode)`` chooses: ``"auto"`` (the default) starts the child where this process may
run on more than one core (:func:`softgrasp.linalg.threads.choose_threads`: a fixed rule, not the
machine's momentary load; one core would run the child's start-up instead of the caller's work),
``"child"`` always, ``"inline"`` never (every figure drawn in the caller's process).
"""

from __future__ import annotations

import os
import pickle
import socket
import subprocess
import sys
from pathlib import Path
from types import TracebackType
from typing import IO, Any

__all__ = ["FigureWorker"]


def _portable(exc: BaseException) -> BaseException:
    """``exc`` if it survives pickling (the parent re-raises it as it is), else a RuntimeError
    naming it."""
    try:
        pickle.loads(pickle.dumps(exc))
    except Exception:  # noqa: BLE001 - any failure to pickle means: send a description instead
        return RuntimeError(f"{type(exc).__name__}: {exc}")
    return exc


def _draw(plots: Any, job: tuple[str, tuple[Any, ...], dict[str, Any]]) -> BaseException | None:
    """Draw one job ``(name, args, kwargs)`` with the figure functions ``plots``; its failure, or
    None."""
    name, args, kwargs = job
    try:
        getattr(plots, name)(*args, **kwargs)
    except Exception as exc:  # noqa: BLE001 - every failure goes back to the caller
        return exc
    return None


def _warm_up(plots: Any) -> None:
    """Import pyplot and the 3-D axes and draw one text, so that the fonts are loaded before the
    first job comes."""
    plt = plots._figure()
    fig = plt.figure()
    fig.add_subplot(projection="3d").set_title("softgrasp")
    fig.canvas.draw()
    plt.close(fig)


def serve(jobs: IO[bytes], answers: IO[bytes]) -> None:
    """The child's loop: load the figure functions, then draw each job ``(name, args, kwargs)``
    read from ``jobs`` until ``None`` or the end of the stream, writing ``None`` or the exception
    for each to ``answers``."""
    try:
        from softgrasp.viz import plots

        _warm_up(plots)
        broken: BaseException | None = None
    except BaseException as exc:  # noqa: BLE001 - reported with the first job
        plots, broken = None, exc
    while True:
        try:
            job = pickle.load(jobs)
        except EOFError:
            return
        if job is None:
            return
        answer = broken if broken is not None else _draw(plots, job)
        pickle.dump(None if answer is None else _portable(answer), answers)
        answers.flush()


#: The figure modes of :class:`FigureWorker`.
MODES = ("auto", "child", "inline")


def _want_child(mode: str) -> bool:
    """Whether to start the child for ``mode`` (see the module's text)."""
    if mode not in MODES:
        raise ValueError(f"unknown figure mode {mode!r} (use one of {', '.join(MODES)})")
    if mode != "auto":
        return mode == "child"
    from softgrasp.linalg.threads import choose_threads

    return choose_threads() >= 2  # this process's core and another


class FigureWorker:
    """A child process that draws :mod:`softgrasp.viz.plots` figures (see the module's text);
    ``mode``: ``"auto"``, ``"child"`` or ``"inline"``.

    Use it as a context manager, so that the child is stopped whatever happens::

        with FigureWorker() as figures:
            result = compute()
            figures.draw("plot_plan_forces", x, y, names, out / "forces.png")
            write_other_files(result)
            figures.finish()
    """

    def __init__(self, mode: str = "auto", *, start: bool = True) -> None:
        self._jobs: list[tuple[str, tuple[Any, ...], dict[str, Any]]] = []
        self._done = 0  # jobs drawn (here or there) and answered, in order
        self._proc: subprocess.Popen[bytes] | None = None
        self._sock: socket.socket | None = None
        self._answers: IO[bytes] | None = None
        self._child = _want_child(mode)  # (checked now: a bad mode fails at once)
        if start:
            self.start()

    def start(self) -> None:
        """Start the child, if ``mode`` wants one and it is not started yet (a worker made with
        ``start=False`` starts it here, or at its first figure)."""
        if not self._child:
            return  # finish() draws the figures here
        self._child = False  # one child at most
        env = dict(os.environ)
        # The child imports this softgrasp, wherever it was imported from.
        root = str(Path(__file__).resolve().parents[2])
        env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH", "")) if p)
        try:
            mine, theirs = socket.socketpair()
        except OSError:
            return  # no child: finish() draws the figures here
        try:
            with theirs:
                self._proc = subprocess.Popen(
                    [sys.executable, "-m", "softgrasp.viz.worker"],
                    stdin=theirs.fileno(),
                    stdout=theirs.fileno(),
                    stderr=subprocess.DEVNULL,
                    env=env,
                )
        except OSError:
            mine.close()
            return
        self._sock = mine
        self._answers = mine.makefile("rb")

    @property
    def in_child(self) -> bool:
        """Whether a child process draws the figures (False: they are drawn in this process)."""
        return self._proc is not None

    def draw(self, name: str, *args: Any, **kwargs: Any) -> None:
        """Queue the figure function ``softgrasp.viz.plots.<name>(*args, **kwargs)``."""
        self.start()
        self._jobs.append((name, args, kwargs))
        if self._sock is not None:
            try:
                self._sock.sendall(pickle.dumps((name, args, kwargs)), socket.MSG_NOSIGNAL)
            except OSError:  # the child is gone: finish() draws it here
                self._stop(kill=True)

    def finish(self) -> None:
        """Wait until every queued figure is written; raise the first failure."""
        first: BaseException | None = None
        while self._done < len(self._jobs):
            error = self._answer() if self._answers is not None else self._draw_here(self._done)
            self._done += 1
            if error is not None and first is None:
                first = error
        self._stop()
        if first is not None:
            raise first

    def _answer(self) -> BaseException | None:
        """The child's answer for the next job; where the child died, that job drawn here."""
        assert self._answers is not None
        try:
            answer = pickle.load(self._answers)
        except (EOFError, OSError, pickle.UnpicklingError):
            self._stop(kill=True)  # the child died: this job and the rest are drawn here
            return self._draw_here(self._done)
        return answer if isinstance(answer, BaseException) else None

    def _draw_here(self, index: int) -> BaseException | None:
        from softgrasp.viz import plots

        return _draw(plots, self._jobs[index])

    def _stop(self, kill: bool = False) -> None:
        """End the child: end its input (it exits by itself) or, with ``kill``, kill it."""
        proc, sock, answers = self._proc, self._sock, self._answers
        self._proc = self._sock = self._answers = None
        if proc is None:
            return
        if kill:
            proc.kill()
        if sock is not None:
            try:
                sock.shutdown(socket.SHUT_WR)
            except OSError:
                pass
        try:
            proc.wait(timeout=10.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        if answers is not None:
            answers.close()
        if sock is not None:
            sock.close()

    def close(self) -> None:
        """Stop the child (a failed command): at once when it has no figure to draw, else once the
        figures queued are written (no temporary file is left behind)."""
        self._stop(kill=self._done >= len(self._jobs))

    def __enter__(self) -> FigureWorker:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


if __name__ == "__main__":  # pragma: no cover - the child process
    # The answers go to a copy of the socket; whatever else would write to standard output (a
    # library's print, C code) goes to standard error instead and cannot corrupt them.
    answers = os.fdopen(os.dup(sys.stdout.fileno()), "wb")
    sys.stdout.flush()
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())
    serve(sys.stdin.buffer, answers)
    # Every answer is written and every figure file closed: the interpreter's teardown of
    # Matplotlib (about 0.15 s) would only delay the caller, which waits for this process's end.
    answers.close()
    sys.stderr.flush()
    os._exit(0)
