"""Explicit time integration of a scene to a final time, and settling to rest.

The equations of motion are the first-order system

    x' = v,    v' = a(x, v, t) = F(x, v, t; contacts) / m                                  (1)

with F = :meth:`Scene.forces` (internal springs, volume term and dampers, gravity, interactions)
and lumped node masses m. The friction state of the contacts is frozen during a step; after every
accepted step it is advanced with :meth:`Scene.update_contacts` (the stick/slip update of the
paper's Algorithm 1). :func:`simulate` drives an integrator to a final time with blow-up detection
(:class:`~softgrasp.sim.stability.BlowupMonitor`); :func:`settle` runs until the body is at rest.

:func:`simulate` runs RK4 on scenes of planes and fingertips in compiled chunks of many steps
(:class:`softgrasp.sim.fused.step.FusedStepper`: the same trajectory to round-off, the same
callbacks, progress reports and blow-up errors); other methods and interactions take the per-step
loop.

Everything here is numerical: nothing is printed; ``progress`` callbacks let a front end draw bars.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
from numpy.typing import NDArray

from softgrasp.errors import NotConverged, SimulationUnstable
from softgrasp.sim.fused.run import fused_unsupported, simulate_fused
from softgrasp.sim.integrators import (
    RK4,
    DormandPrince45,
    Integrator,
    SemiImplicitEuler,
    make_integrator,
    max_speed,
)
from softgrasp.sim.scene import Scene, State
from softgrasp.sim.stability import (
    BlowupMonitor,
    stable_time_step,
)

__all__ = [
    "RK4",
    "DormandPrince45",
    "Integrator",
    "SemiImplicitEuler",
    "fused_unsupported",
    "make_integrator",
    "max_speed",
    "settle",
    "simulate",
]

Array = NDArray[np.float64]


def _check_time_step(scene: Scene, integ: Integrator, dt: float | None, check_dt: bool) -> float:
    """The step size to use: the stable bound by default; an error if ``dt`` exceeds it."""
    bound = stable_time_step(scene, integ.method)
    if dt is None:
        return bound
    if not (math.isfinite(dt) and dt > 0):
        raise ValueError(f"time step must be positive and finite, got {dt}")
    if check_dt and not integ.adaptive and dt > bound:
        raise SimulationUnstable(
            f"dt = {dt:.3g} s exceeds the stable time step {bound:.3g} s of {integ.method} for this scene "
            f"(Gershgorin bound, safety 0.9); use dt <= {bound:.3g} s or pass check_dt=False",
            bound,
        )
    return dt


def _guarded_step(
    scene: Scene, state: State, integ: Integrator, dt: float, monitor: BlowupMonitor | None
) -> State:
    """One step followed by the monitor's checks.

    Floating-point overflow and invalid-operation warnings are silenced during the step: a blow-up
    (e.g. a tet flattened in an intermediate stage makes the volume barrier explode) surfaces as
    non-finite positions or velocities, which the monitor turns into :class:`SimulationUnstable`.
    """
    t_prev = state.t
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        new = integ.step(scene, state, dt)
        if monitor is not None:
            monitor.after_step(new, new.t - t_prev)
    return new


def _advance(
    scene: Scene, state: State, integ: Integrator, dt: float, t_end: float, monitor: BlowupMonitor | None
) -> Iterator[State]:
    """Yield the state after every accepted step until ``t_end`` [s].

    Fixed-step methods take ``n = ceil((t_end - t0) / dt)`` equal steps so they land on t_end.
    """
    t0 = state.t
    span = t_end - t0
    if span <= 0:
        return
    if not integ.adaptive:
        n = max(1, math.ceil(span / dt * (1.0 - 1e-12)))
        h = span / n
        for _ in range(n - 1):
            state = _guarded_step(scene, state, integ, h, monitor)
            yield state
        # Land exactly on t_end: the last step is t_end - t, not h, to avoid accumulated round-off.
        yield _guarded_step(scene, state, integ, t_end - state.t, monitor)
        return
    h = dt
    while state.t < t_end:
        remaining = t_end - state.t
        if remaining <= 1e-12 * max(1.0, abs(t_end)):
            break
        state = _guarded_step(scene, state, integ, min(h, remaining), monitor)
        nxt = getattr(integ, "dt_next", None)
        h = dt if nxt is None else min(nxt, dt)
        yield state


def simulate(
    scene: Scene,
    state: State,
    t_end: float,
    *,
    method: str | Integrator = "rk4",
    dt: float | None = None,
    callback: Callable[[State], None] | None = None,
    every: int = 1,
    progress: Callable[[float], None] | None = None,
    check_dt: bool = True,
    check_every: int = 10,
    fused: bool | None = None,
    **options: Any,
) -> State:
    """Integrate Eq. (1) from ``state`` to time ``t_end``.

    Parameters
    ----------
    scene:
        Body and interactions.
    state:
        Initial state (``state.t`` is the start time [s]).
    t_end:
        Final time [s]; the returned state has ``t == t_end`` (to round-off).
    method:
        ``rk4`` (default), ``semi-implicit``, ``dopri``/``rk45``, or an :class:`Integrator`.
    dt:
        Time step [s]; default the stable bound :func:`stable_time_step`. Fixed-step methods take
        equal steps of at most dt; for ``dopri`` it is the largest step (also capped at the stable
        bound) and the first one tried.
    callback:
        Called as ``callback(state)`` with the initial state, after every ``every``-th step and
        with the final state (for recording).
    every:
        Steps between callbacks (>= 1).
    progress:
        Called with the completed fraction of the time span in [0, 1] (about 100 times).
    check_dt:
        If true, a fixed-step ``dt`` above the stable bound raises at once.
    check_every:
        Steps between the volume and energy checks of the blow-up monitor.
    fused:
        Whether to run the steps in compiled chunks (:mod:`softgrasp.sim.fused.step`): ``None``
        (default) does so when it can -- RK4, only :class:`~softgrasp.physics.planes.PlaneContact` and
        :class:`~softgrasp.physics.fingertip.contact.FingertipContact` interactions (at most one of the
        latter), a polynomial stress-strain law; ``False`` never (the per-step path); ``True``
        requires it (``ValueError`` when it cannot). Both paths give the same trajectory to
        round-off, with the same callbacks, progress reports and blow-up checks.
    options:
        Tolerances etc. of :class:`DormandPrince45` when ``method`` is a name.

    Returns
    -------
    State
        The state at ``t_end``.

    Raises
    ------
    SimulationUnstable
        ``dt`` above the stable bound (with ``check_dt``), or the integration blew up (non-finite
        values, an inverted tet, runaway energy; see :class:`BlowupMonitor`). ``suggested_dt`` on
        the exception gives a step to retry with.
    """
    if every < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    integ = make_integrator(method, **options)
    scene = scene.frozen(state.t)  # time-dependent contact data held through the run
    h = _check_time_step(scene, integ, dt, check_dt)
    reason = fused_unsupported(scene, integ) if fused is not False else "disabled"
    if fused and reason is not None:
        raise ValueError(f"the fused stepper cannot run this simulation: {reason}")
    monitor = BlowupMonitor(scene, state, integ.method, check_every=check_every)
    if reason is None:
        return simulate_fused(scene, state, h, t_end, monitor, callback, every, progress)
    t0, span = state.t, t_end - state.t
    if callback is not None:
        callback(state)
    next_report = 0.0
    steps = 0
    last_called = 0
    current = state
    for current in _advance(scene, state, integ, h, t_end, monitor):
        steps += 1
        if callback is not None and steps % every == 0:
            callback(current)
            last_called = steps
        if progress is not None and span > 0:
            frac = min(1.0, (current.t - t0) / span)
            if frac >= next_report:
                progress(frac)
                next_report = frac + 0.01
    if steps:
        monitor.check(current, h)
    if callback is not None and steps and last_called != steps:
        callback(current)
    if progress is not None:
        progress(1.0)
    return current


def settle(
    scene: Scene,
    state: State,
    *,
    t_max: float,
    tol_velocity: float,
    hold: float | None = None,
    method: str | Integrator = "rk4",
    dt: float | None = None,
    check_dt: bool = True,
    check_every: int = 10,
    **options: Any,
) -> State:
    """Integrate until every node is slower than ``tol_velocity`` for ``hold`` seconds.

    Used to let a body come to rest (e.g. on the table) before grasping.

    Parameters
    ----------
    scene, state:
        Scene and initial state.
    t_max:
        Longest simulated time [s] allowed (from ``state.t``).
    tol_velocity:
        Speed [m/s] every node must stay below.
    hold:
        How long [s] the speeds must stay below the tolerance; default two periods of the body's
        fundamental mode, ``4 pi / omega_1`` (:attr:`Body.fundamental_frequency`).
    method, dt, check_dt, check_every, options:
        As in :func:`simulate`.

    Returns
    -------
    State
        The first state at which the speeds have stayed below the tolerance for ``hold``.

    Raises
    ------
    NotConverged
        Not at rest after ``t_max``.
    SimulationUnstable
        As in :func:`simulate`.
    """
    if not (tol_velocity > 0 and t_max > 0):
        raise ValueError("tol_velocity and t_max must be > 0")
    if hold is None:
        hold = 4.0 * math.pi / scene.body.fundamental_frequency
    integ = make_integrator(method, **options)
    h = _check_time_step(scene, integ, dt, check_dt)
    monitor = BlowupMonitor(scene, state, integ.method, check_every=check_every)
    t0 = state.t
    quiet_since: float | None = state.t if max_speed(state.v) < tol_velocity else None
    current = state
    for current in _advance(scene, state, integ, h, t0 + t_max, monitor):
        if max_speed(current.v) < tol_velocity:
            if quiet_since is None:
                quiet_since = current.t
            if current.t - quiet_since >= hold * (1.0 - 1e-9):
                monitor.check(current, h)
                return current
        else:
            quiet_since = None
    raise NotConverged(
        f"body not at rest after {t_max:.4g} s: a node moves at {max_speed(current.v):.3g} m/s "
        f"(tolerance {tol_velocity:.3g} m/s held for {hold:.3g} s); increase t_max or damping"
    )
