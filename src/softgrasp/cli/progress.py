"""A command's progress by phase on stderr: on a terminal one bar, labelled by the phase, whose
fraction never goes backwards; elsewhere (a pipe, a file, a test) one line per phase and no bar.

``softgrasp plan`` passes through meshing, loading (or, on a first run, compiling) the kernels,
the planner's phases (initial grasp, closing, hold check, set-points: :mod:`softgrasp.grasp.progress`)
and the figures. Each has a share of the bar (:data:`PLAN_SHARES`; compiling takes most of a
first run). Phases shown on the bar only (``quiet``) print no line: those during which input can
still be refused, so that a refused input stays one line on stderr.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from softgrasp.interrupt import raise_if_interrupted

__all__ = ["PLAN_SHARES", "PhaseBar", "kernels_phase"]

#: The shares of ``softgrasp plan``'s bar: (start, end) of each part, as fractions of the whole.
PLAN_SHARES = {
    "meshing": (0.0, 0.05),
    "loading kernels": (0.05, 0.1),
    "compiling kernels": (0.05, 0.6),  # then the planning's part starts at its end
    "planning": (0.1, 0.95),
    "figures": (0.95, 1.0),
}


class PhaseBar:
    """A command's progress on stderr: :meth:`phase` as each phase starts, :meth:`within` for the
    fraction done inside one; :meth:`close` at the end (also on failure).

    Parameters
    ----------
    command: the command's name, the bar's label.  shares: (start, end) of each phase's part of
        the bar, by phase name (:data:`PLAN_SHARES`); a phase not in it keeps the bar where it is.
    tty: whether stderr is a terminal (default: ask it).
    """

    def __init__(
        self,
        command: str,
        shares: dict[str, tuple[float, float]] | None = None,
        tty: bool | None = None,
    ) -> None:
        self.command, self.shares = command, dict(shares or {})
        self.tty = sys.stderr.isatty() if tty is None else tty
        self.done, self.name = 0.0, ""
        self.phases: list[str] = []
        self._bar = None
        if self.tty:
            from tqdm import tqdm

            self._bar = tqdm(
                total=1000,
                desc=command,
                leave=False,
                file=sys.stderr,
                bar_format="{desc}: {percentage:3.0f}%|{bar}| {elapsed}",
            )

    def phase(self, name: str, label: str | None = None, *, quiet: bool = False) -> None:
        """Phase ``name`` starts: the bar says ``label`` (default the name) and moves to the
        phase's start; off a terminal one line ``softgrasp: COMMAND: LABEL`` unless ``quiet``.
        A Ctrl-C received before (:mod:`softgrasp.interrupt`) stops the command here."""
        raise_if_interrupted()
        self.name = name
        self.phases.append(name)
        text = label or name
        if self._bar is not None:
            self._bar.set_description_str(f"{self.command}: {text}", refresh=False)
        elif not quiet:
            print(f"softgrasp: {self.command}: {text}", file=sys.stderr, flush=True)
        self.report(self.shares.get(name, (self.done, self.done))[0])

    def relabel(self, text: str) -> None:
        """The current phase goes on under a new label: the bar says ``text``; off a terminal one
        line ``softgrasp: COMMAND: TEXT``."""
        if self._bar is not None:
            self._bar.set_description_str(f"{self.command}: {text}", refresh=True)
        else:
            print(f"softgrasp: {self.command}: {text}", file=sys.stderr, flush=True)

    def report(self, fraction: float) -> None:
        """The whole is ``fraction`` done; a smaller fraction than before leaves the bar."""
        self.done = max(self.done, min(float(fraction), 1.0))
        if self._bar is not None:
            self._bar.n = int(round(1000 * self.done))
            self._bar.refresh()

    def within(self, name: str) -> Callable[[float], None]:
        """A callback taking the fraction done of phase (or part) ``name``: the bar over its share."""

        def update(fraction: float) -> None:
            start, end = self.shares[name]
            self.report(start + (end - start) * min(max(fraction, 0.0), 1.0))

        return update

    @contextmanager
    def part(self, name: str) -> Iterator[Callable[[float], None]]:
        """A part of the work (``planning``) over its share of the bar: yields :meth:`within`'s
        callback; the bar is at the part's end when it ends without an error."""
        yield self.within(name)
        self.within(name)(1.0)

    def write(self, text: str) -> None:
        """Print ``text`` on stdout without breaking the bar (at once, also into a pipe)."""
        if self._bar is not None:
            from tqdm import tqdm

            tqdm.write(text, file=sys.stdout)
            sys.stdout.flush()
        else:
            print(text, flush=True)

    def close(self) -> None:
        """Remove the bar."""
        if self._bar is not None:
            self._bar.close()
            self._bar = None


def kernels_phase(bar: PhaseBar, warm_up) -> None:
    """Wait for the compiled kernels (:class:`softgrasp.cli.warm.WarmUp`) under the phase that
    says what happens: compiling them (a first run) or loading them; nothing when they are
    loaded already."""
    import time

    from softgrasp.cli.warm import COMPILE_TIME_S

    if warm_up is None or not warm_up.is_alive():
        return
    warm_up.checked.wait()
    name = "compiling kernels" if warm_up.cold else "loading kernels"
    if warm_up.cold:
        bar.phase(name, f"compiling kernels (first run only, ~{COMPILE_TIME_S} s)")
        start, end = bar.shares.get(name, (bar.done, bar.done))
        if "planning" in bar.shares:  # the planner's part of the bar starts after the compiling
            bar.shares["planning"] = (end, bar.shares["planning"][1])
    else:
        bar.phase(name)
    t0, expected = time.monotonic(), COMPILE_TIME_S if warm_up.cold else 1.0
    update = bar.within(name) if name in bar.shares else None
    said: set[str] = set()
    while warm_up.is_alive():
        warm_up.join(timeout=0.5)
        if update is not None:  # the expected time's share gone, at most 95 % of the phase
            update(min(0.95, (time.monotonic() - t0) / expected))
        now = warm_up.compiling
        if warm_up.cold and now and now not in said:  # what is being compiled, each named once
            said.add(now)
            bar.relabel(f"compiling kernels: {now}")
