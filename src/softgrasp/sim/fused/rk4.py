"""The fused stepper's compiled loop: classical RK4 steps of a scene, the checks after each.

One call of :func:`advance` takes K steps of :class:`softgrasp.sim.explicit.RK4` on

    x' = v,   v' = (((f_internal(x, v) + m g) + f_planes(x, v, t)) + f_fingers(x, v, t)) / m,

four force evaluations a step with the friction states of the step's start, then the friction
state updates at the new state (planes, then fingertips: :meth:`Scene.update_contacts`), the
forces there (the next step's first stage, and the power, energy and inverted tets the blow-up
monitor's checks need: :mod:`softgrasp.sim.fused.monitor`). The forces are those of
:mod:`softgrasp.sim.fused.body` and :mod:`softgrasp.sim.fused.contacts`.

The workspace ``work`` is ``(fint, info, fplane, ffinger, centres, x_ref, track, p0, near)``: the
internal forces in parts (parts, N, 3) and the parts' sums (parts, 3), the planes' and the
fingertips' forces (N, 3), the fingertip centres, the fingertip broad phase's reference
positions, bookkeeping and near list (:func:`softgrasp.sim.fused.contacts.finger_reach`), the
planes' points now.
"""

from __future__ import annotations

import math

from softgrasp.sim.fused.body import body_forces
from softgrasp.sim.fused.cache import jit
from softgrasp.sim.fused.contacts import finger_forces, finger_step, plane_step
from softgrasp.sim.fused.monitor import F_DT, F_T, STATUS_NONFINITE, STATUS_OK, after_step

__all__ = ["advance", "forces_at"]


@jit
def forces_at(
    x, v, t, body, planes, pl_active, pl_anchor, fingers, fstate, cur, work, parallel
):  # pragma: no cover - compiled
    """All forces at the state (x, v, t) into the workspace, with the friction states as they are
    (as :meth:`softgrasp.sim.scene.Scene.forces` on the state's contacts): before the first step
    and at each RK4 stage."""
    fint, info, fplane, ffinger, centres, x_ref, track, p0, near = work
    body_forces(parallel, x, v, body, False, False, fint, info)
    fplane[:] = 0.0
    ffinger[:] = 0.0
    plane_step(x, v, t, planes, p0, pl_active, pl_anchor, False, fplane)
    if fingers[0]:
        finger_forces(x, v, t, fingers, fstate, cur, x_ref, track, near, centres, ffinger)


@jit
def _acceleration(i, d, m, fint, grav, fplane, ffinger):  # pragma: no cover - compiled
    """Component d of node i's acceleration [m/s^2]: the parts of its internal force summed, plus
    gravity, the planes' and the fingertips' forces, over its mass m."""
    fi = fint[0, i, d]
    for q in range(1, fint.shape[0]):
        fi += fint[q, i, d]
    return (((fi + grav[i, d]) + fplane[i, d]) + ffinger[i, d]) / m


@jit
def _stage(stage, x, v, xs, vs, ax, av, mass, grav, work, h):  # pragma: no cover - compiled
    """Accumulate RK4 stage ``stage`` (1-3) from the forces in the workspace (a_k = F / m at the
    stage state) and set the next stage state, as :meth:`softgrasp.sim.explicit.RK4.step`:
    ``v2 = v + h/2 a1, x2 = x + h/2 v``; ``v3 = v + h/2 a2, x3 = x + h/2 v2``;
    ``v4 = v + h a3, x4 = x + h v3``; sums ``a1 + 2 a2 + 2 a3`` and ``v + 2 v2 + 2 v3`` in that
    order. Updates the largest squared displacement from ``x_ref`` of the stage positions (the
    fingertip broad phase)."""
    fint, info, fplane, ffinger, centres, x_ref, track, p0, near = work
    h2 = 0.5 * h
    u2 = track[1]
    for i in range(x.shape[0]):
        m = mass[i]
        du2 = 0.0
        for d in range(3):
            a = _acceleration(i, d, m, fint, grav, fplane, ffinger)
            if stage == 1:
                av[i, d] = a
                ax[i, d] = v[i, d]
                vs[i, d] = v[i, d] + h2 * a
                xs[i, d] = x[i, d] + h2 * v[i, d]
            elif stage == 2:
                av[i, d] = av[i, d] + 2.0 * a
                ax[i, d] = ax[i, d] + 2.0 * vs[i, d]
                xs[i, d] = x[i, d] + h2 * vs[i, d]
                vs[i, d] = v[i, d] + h2 * a
            else:
                av[i, d] = av[i, d] + 2.0 * a
                ax[i, d] = ax[i, d] + 2.0 * vs[i, d]
                xs[i, d] = x[i, d] + h * vs[i, d]
                vs[i, d] = v[i, d] + h * a
            du = xs[i, d] - x_ref[i, d]
            du2 += du * du
        u2 = max(u2, du2)
    track[1] = u2


@jit
def _finish(x, v, xs, vs, ax, av, mass, grav, work, w):  # pragma: no cover - compiled
    """``x += w (v + 2 v2 + 2 v3 + v4)``, ``v += w (a1 + 2 a2 + 2 a3 + a4)`` (w = h / 6), the
    fourth stage's forces in the workspace. Returns (whether a value became non-finite,
    ``sum m x``); updates the largest squared displacement from ``x_ref``."""
    fint, info, fplane, ffinger, centres, x_ref, track, p0, near = work
    bad = False
    u2 = track[1]
    mx = 0.0
    my = 0.0
    mz = 0.0
    for i in range(x.shape[0]):
        m = mass[i]
        du2 = 0.0
        for d in range(3):
            a = _acceleration(i, d, m, fint, grav, fplane, ffinger)
            xi = x[i, d] + w * (ax[i, d] + vs[i, d])
            vi = v[i, d] + w * (av[i, d] + a)
            x[i, d] = xi
            v[i, d] = vi
            bad |= not (abs(vi) < math.inf and abs(xi) < math.inf)
            du = xi - x_ref[i, d]
            du2 += du * du
        u2 = max(u2, du2)
        mx += m * x[i, 0]
        my += m * x[i, 1]
        mz += m * x[i, 2]
    track[1] = u2
    return bad, mx, my, mz


@jit
def advance(n_steps, h, land, t_end, t, x, v, mass, grav, total_mass, body, planes, pl_active, pl_anchor,
            fingers, fstate, cur, work, have_forces, parallel, monitor_on, mon, msteps, check_every, gvec,
            fail, rk):  # pragma: no cover - compiled  # fmt: skip
    """Up to ``n_steps`` RK4 steps of ``h`` [s] from time ``t`` (the last one ending at ``t_end``
    when ``land``); see :meth:`softgrasp.sim.fused.step.FusedStepper.advance`. ``rk`` holds the
    stage state and the weighted sums of the stage velocities and accelerations (N, 3) each.

    Returns (status, steps taken, t, current fingertip state buffer, monitored steps)."""
    fint, info, fplane, ffinger, centres, x_ref, track, p0, near = work
    xs, vs, ax, av = rk
    if not have_forces:
        forces_at(x, v, t, body, planes, pl_active, pl_anchor, fingers, fstate, cur, work, parallel)
    for s in range(n_steps):
        t_prev = t
        dt = t_end - t if (land and s == n_steps - 1) else h
        h2 = 0.5 * dt
        _stage(1, x, v, xs, vs, ax, av, mass, grav, work, dt)
        forces_at(xs, vs, t + h2, body, planes, pl_active, pl_anchor, fingers, fstate, cur, work, parallel)
        _stage(2, x, v, xs, vs, ax, av, mass, grav, work, dt)
        forces_at(xs, vs, t + h2, body, planes, pl_active, pl_anchor, fingers, fstate, cur, work, parallel)
        _stage(3, x, v, xs, vs, ax, av, mass, grav, work, dt)
        forces_at(xs, vs, t + dt, body, planes, pl_active, pl_anchor, fingers, fstate, cur, work, parallel)
        bad, mx, my, mz = _finish(x, v, xs, vs, ax, av, mass, grav, work, dt / 6.0)
        t = t + dt
        if bad:
            fail[F_T] = t
            fail[F_DT] = t - t_prev
            return STATUS_NONFINITE, s + 1, t, cur, msteps + 1
        # the friction states after the step, then the forces at the new state
        fplane[:] = 0.0
        ffinger[:] = 0.0
        power = plane_step(x, v, t, planes, p0, pl_active, pl_anchor, True, fplane)
        if fingers[0]:
            cur, p_finger = finger_step(x, v, t, fingers, fstate, cur, x_ref, track, near, centres, ffinger,
                                        monitor_on)  # fmt: skip
            power += p_finger
        msteps += 1
        check = monitor_on and msteps % check_every == 0
        e_int, count, first = body_forces(parallel, x, v, body, check, check, fint, info)
        if monitor_on:
            status = after_step(
                x, v, t, t_prev, mass, total_mass, gvec, mon, fail, power, mx, my, mz, check, e_int, count,
                first,
            )  # fmt: skip
            if status != STATUS_OK:
                return status, s + 1, t, cur, msteps
    return STATUS_OK, n_steps, t, cur, msteps
