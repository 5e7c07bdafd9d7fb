"""The blow-up monitor's checks inside the fused stepper (:class:`softgrasp.sim.stability.BlowupMonitor`).

The monitor's bookkeeping lives in a float array (slots ``M_*``): the interactions' work
integrated by the trapezoidal rule from their power at the states the steps reach, its absolute
value, the largest work of gravity on the centre of mass, and the monitor's constants. Every
``check_every`` steps the checks run on the force evaluation at the new state: no inverted tet,
and an energy ``kinetic + elastic - m g . x`` that exceeds its start plus the work done by no more
than the monitor's factor times its scale. A failed check is a status code with its details in
the failure array (slots ``F_*``); the caller raises the same
:class:`~softgrasp.errors.SimulationUnstable` as the per-step path.
"""

from __future__ import annotations

from dataclasses import dataclass

from softgrasp.sim.fused.cache import jit

__all__ = ["STATUS_ENERGY", "STATUS_INVERTED", "STATUS_NONFINITE", "STATUS_OK", "Failure", "after_step"]

#: Status codes of :meth:`softgrasp.sim.fused.step.FusedStepper.advance`.
STATUS_OK = 0
STATUS_NONFINITE = 1
STATUS_INVERTED = 2
STATUS_ENERGY = 3

# Slots of the monitor's float array.
M_T, M_POWER, M_WORK, M_ABS, M_GRAV, M_E0, M_SCALE0, M_FACTOR, M_COM0 = 0, 1, 2, 3, 4, 5, 6, 7, 8
M_SIZE = 11
# Slots of the failure array.
F_T, F_DT, F_COUNT, F_FIRST, F_EXCESS, F_SCALE = 0, 1, 2, 3, 4, 5
F_SIZE = 6


@dataclass
class Failure:
    """What stopped :meth:`softgrasp.sim.fused.step.FusedStepper.advance`.

    Attributes
    ----------
    status: :data:`STATUS_NONFINITE`, :data:`STATUS_INVERTED` or :data:`STATUS_ENERGY`.
    t: time of the failing state [s].  dt: length of the step that reached it [s].
    count, first: inverted tets and the lowest mesh index among them (:data:`STATUS_INVERTED`).
    excess, scale: the energy test's excess and scale [J] (:data:`STATUS_ENERGY`).
    """

    status: int
    t: float
    dt: float
    count: int = 0
    first: int = -1
    excess: float = 0.0
    scale: float = 0.0


@jit
def after_step(x, v, t, t_prev, mass, total_mass, gvec, mon, fail, power, mx, my, mz, check, e_int, count,
               first):  # pragma: no cover - compiled  # fmt: skip
    """:meth:`softgrasp.sim.stability.BlowupMonitor.after_step` for the state (x, v, t) reached by a
    step from ``t_prev``: ``power`` of the interactions there, ``sum m x`` = (mx, my, mz), and when
    ``check``, the inverted tets (``count``, ``first``) and elastic energy ``e_int`` of the force
    evaluation at that state. Returns a status; the failure's details go to ``fail``."""
    hb = t - mon[M_T]
    mon[M_WORK] += 0.5 * (mon[M_POWER] + power) * hb
    mon[M_ABS] += 0.5 * (abs(mon[M_POWER]) + abs(power)) * hb
    mon[M_POWER] = power
    mon[M_T] = t
    dz = (
        (mx / total_mass - mon[M_COM0]) * gvec[0]
        + (my / total_mass - mon[M_COM0 + 1]) * gvec[1]
        + (mz / total_mass - mon[M_COM0 + 2]) * gvec[2]
    ) * total_mass
    mon[M_GRAV] = max(mon[M_GRAV], abs(dz))
    if not check:
        return STATUS_OK
    if count > 0:
        fail[F_T] = t
        fail[F_DT] = t - t_prev
        fail[F_COUNT] = count
        fail[F_FIRST] = first
        return STATUS_INVERTED
    kin = 0.0
    pot = 0.0
    for i in range(x.shape[0]):
        kin += mass[i] * (v[i, 0] * v[i, 0] + v[i, 1] * v[i, 1] + v[i, 2] * v[i, 2])
        pot += mass[i] * (x[i, 0] * gvec[0] + x[i, 1] * gvec[1] + x[i, 2] * gvec[2])
    excess = (0.5 * kin + e_int - pot) - mon[M_E0] - mon[M_WORK]
    scale = max(mon[M_SCALE0], mon[M_ABS], mon[M_GRAV])
    if not excess <= mon[M_FACTOR] * scale:
        fail[F_T] = t
        fail[F_DT] = t - t_prev
        fail[F_EXCESS] = excess
        fail[F_SCALE] = scale
        return STATUS_ENERGY
    return STATUS_OK
