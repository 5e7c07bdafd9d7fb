"""Running :func:`softgrasp.sim.explicit.simulate` on the fused stepper: chunks, threads, read-outs.

:func:`simulate_fused` takes the same equal steps as the per-step loop in compiled chunks of at
most :data:`FUSED_CHUNK` steps (:class:`softgrasp.sim.fused.step.FusedStepper`), each chunk ending
where the loop would call back or report progress; :func:`fused_unsupported` says when it cannot
run a simulation; :func:`fused_threads` chooses its threads; :class:`FusedRun` reads the stepper out as :class:`~softgrasp.sim.scene.State`. Numba is
imported with the stepper, at the first fused run.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from softgrasp.errors import SimulationUnstable
from softgrasp.sim.scene import Scene, State
from softgrasp.sim.stability import BlowupMonitor

__all__ = ["FUSED_CHUNK", "FusedRun", "fused_threads", "fused_unsupported", "simulate_fused"]

#: Most steps one compiled call takes (keeps Ctrl-C responsive: ~0.1 s at 20 000 steps/s).
FUSED_CHUNK = 2000


def fused_unsupported(scene: Scene, integ: Any) -> str | None:
    """Why :func:`softgrasp.sim.explicit.simulate` cannot run ``scene`` with the integrator ``integ``
    in compiled chunks (:class:`softgrasp.sim.fused.step.FusedStepper`), or None when it can."""
    from softgrasp.sim.integrators import RK4

    if type(integ) is not RK4:
        return f"method {integ.method!r} (RK4 is fused)"
    from softgrasp.physics.fingertip.contact import FingertipContact
    from softgrasp.physics.planes import PlaneContact

    planes, fingers = [], []
    for inter in scene.interactions:
        if type(inter) is PlaneContact:
            planes.append(inter)
        elif type(inter) is FingertipContact:
            fingers.append(inter)
        else:
            return f"interaction {getattr(inter, 'name', '?')!r} of type {type(inter).__name__}"
    from softgrasp.sim.fused.step import supported

    return supported(scene.body, planes, fingers)


def fused_threads() -> int:
    """How many of Numba's threads the fused stepper computes on: the one thread setting
    (:func:`softgrasp.linalg.threads.choose_threads`: ``SOFTGRASP_THREADS`` or the cores this
    process may use), at most :data:`softgrasp.sim.fused.step.PARTS`. The trajectory does not
    depend on it (the parts and their sums are the same on one thread or two), and neither does
    the choice depend on how busy the machine is."""
    from softgrasp.linalg.threads import choose_threads
    from softgrasp.sim.fused.step import PARTS

    return max(1, min(PARTS, choose_threads()))


class FusedRun:
    """A :class:`~softgrasp.sim.fused.step.FusedStepper` on a scene, read out as :class:`State`."""

    def __init__(self, scene: Scene, state: State, monitor: BlowupMonitor | None) -> None:
        from softgrasp.physics.fingertip.contact import FingertipContact
        from softgrasp.sim.fused.step import FusedStepper

        self.template = state
        self.planes = [i for i, inter in enumerate(scene.interactions) if type(inter) is not FingertipContact]
        fingers = [i for i, inter in enumerate(scene.interactions) if type(inter) is FingertipContact]
        self.finger = fingers[0] if fingers else None
        inter, contacts = scene.interactions, state.contacts
        self.stepper = FusedStepper(
            scene.body,
            [inter[i] for i in self.planes],
            [contacts[i] for i in self.planes],
            None if self.finger is None else inter[self.finger],
            None if self.finger is None else contacts[self.finger],
            state.x,
            state.v,
            state.t,
            monitor,
        )

    def state(self) -> State:
        """The current state (copies)."""
        st = self.stepper
        x, v, t = st.arrays()
        contacts = list(self.template.contacts)
        for i, ps in zip(self.planes, st.plane_states([contacts[i] for i in self.planes]), strict=True):
            contacts[i] = ps
        if self.finger is not None:
            contacts[self.finger] = st.finger_state(contacts[self.finger])
        return State(x, v, t, tuple(contacts))


def _fused_error(monitor: BlowupMonitor, failure: Any) -> SimulationUnstable:
    """The :class:`SimulationUnstable` the per-step path raises for the stepper's ``failure``."""
    from softgrasp.sim.fused import step

    if failure.status == step.STATUS_NONFINITE:
        reason = "positions or velocities became non-finite"
    elif failure.status == step.STATUS_INVERTED:
        reason = monitor.inverted_reason(failure.count, failure.first)
    else:
        reason = monitor.energy_reason(failure.excess, failure.scale)
    return monitor.error(failure.t, failure.dt, reason)


def simulate_fused(
    scene: Scene,
    state: State,
    dt: float,
    t_end: float,
    monitor: BlowupMonitor,
    callback: Callable[[State], None] | None,
    every: int,
    progress: Callable[[float], None] | None,
) -> State:
    """:func:`softgrasp.sim.explicit.simulate` for RK4 in compiled chunks: the same equal steps (the last
    one landing on ``t_end``), callbacks, progress reports and checks as the per-step loop, each
    chunk ending where the loop would call back or report."""
    t0, span = state.t, t_end - state.t
    if callback is not None:
        callback(state)
    if span <= 0:
        if progress is not None:
            progress(1.0)
        return state
    n = max(1, math.ceil(span / dt * (1.0 - 1e-12)))
    h = span / n
    run = FusedRun(scene, state, monitor)
    done = 0
    next_report = 0.0
    last_called = 0
    run.stepper.threads = fused_threads()
    while done < n:
        target = min(n, done + FUSED_CHUNK)
        if callback is not None:
            target = min(target, (done // every + 1) * every)
        if progress is not None:
            target = min(target, max(done + 1, math.ceil(next_report * n)))
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            taken = run.stepper.advance(target - done, h, t_end if target == n else None)
        done += taken
        if run.stepper.failure is not None:
            raise _fused_error(monitor, run.stepper.failure)
        if callback is not None and done % every == 0:
            callback(run.state())
            last_called = done
        if progress is not None:
            frac = min(1.0, (run.stepper.t - t0) / span)
            if frac >= next_report:
                progress(frac)
                next_report = frac + 0.01
    current = run.state()
    monitor.check(current, dt)
    if callback is not None and last_called != done:
        callback(current)
    if progress is not None:
        progress(1.0)
    return current
