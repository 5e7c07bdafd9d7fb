"""Explicit one-step integrators of a scene: semi-implicit Euler, classic RK4 (the paper's
explicit Runge-Kutta) and adaptive Dormand-Prince 5(4) (Matlab's ode45).

The equations of motion are the first-order system

    x' = v,    v' = a(x, v, t) = F(x, v, t; contacts) / m                                  (1)

with F = :meth:`Scene.forces` (internal springs, volume term and dampers, gravity, interactions)
and lumped node masses m. The friction state of the contacts is frozen during a step; after every
accepted step it is advanced with :meth:`Scene.update_contacts` (the stick/slip update of the
paper's Algorithm 1). :func:`softgrasp.sim.explicit.simulate` drives these integrators.
"""

from __future__ import annotations

import dataclasses
import math
from abc import ABC, abstractmethod
from typing import Any

import numpy as np
from numpy.typing import NDArray

from softgrasp.sim.scene import Scene, State
from softgrasp.sim.stability import canonical_method, stable_time_step, unstable_error

__all__ = ["RK4", "DormandPrince45", "Integrator", "SemiImplicitEuler", "make_integrator", "max_speed"]

Array = NDArray[np.float64]


def _acceleration(scene: Scene, x: Array, v: Array, t: float, contacts: tuple[Any, ...]) -> Array:
    """Right-hand side a = F / m of Eq. (1) [m/s^2], (N, 3)."""
    return scene.forces(x, v, t, contacts) / scene.body.mass[:, None]


def _finish(scene: Scene, state: State, x: Array, v: Array, dt: float) -> State:
    """The state after an accepted step: new x, v, t and updated friction states."""
    t = state.t + dt
    return State(x, v, t, scene.update_contacts(x, v, t, state.contacts))


def max_speed(v: Array) -> float:
    """Largest node speed [m/s] of velocities ``v`` (N, 3)."""
    return float(np.sqrt(np.max(np.einsum("ij,ij->i", v, v))))


class Integrator(ABC):
    """One step of an explicit method for Eq. (1).

    Attributes
    ----------
    method: canonical method name used for stability bounds (``rk4``, ``dopri``,
        ``semi-implicit``).
    adaptive: whether :meth:`step` may take a shorter step than asked (then ``state.t`` tells).
    """

    method: str = ""
    adaptive: bool = False

    @abstractmethod
    def step(self, scene: Scene, state: State, dt: float) -> State:
        """Advance ``state`` by ``dt`` [s] (adaptive methods: by at most ``dt``); friction states
        are updated after the step."""


class SemiImplicitEuler(Integrator):
    """Semi-implicit (symplectic) Euler: ``v += dt a(x, v); x += dt v``.

    First order; for undamped bodies it conserves linear and angular momentum exactly and keeps the
    energy error bounded (O(dt), no drift). Stable for ``dt < 2 / rho`` (see
    :mod:`softgrasp.sim.stability`).
    """

    method = "semi-implicit"

    def step(self, scene: Scene, state: State, dt: float) -> State:
        v = state.v + dt * _acceleration(scene, state.x, state.v, state.t, state.contacts)
        x = state.x + dt * v
        return _finish(scene, state, x, v, dt)


class RK4(Integrator):
    """Classical fourth-order Runge-Kutta on Eq. (1), four force evaluations per step.

    Stable for ``dt < 2.8 / omega_max`` without damping and ``dt < 2.5 / rho`` in general.
    """

    method = "rk4"

    def step(self, scene: Scene, state: State, dt: float) -> State:
        x, v, t, c = state.x, state.v, state.t, state.contacts
        h2 = 0.5 * dt
        a1 = _acceleration(scene, x, v, t, c)
        v2 = v + h2 * a1
        a2 = _acceleration(scene, x + h2 * v, v2, t + h2, c)
        v3 = v + h2 * a2
        a3 = _acceleration(scene, x + h2 * v2, v3, t + h2, c)
        v4 = v + dt * a3
        a4 = _acceleration(scene, x + dt * v3, v4, t + dt, c)
        x_new = x + (dt / 6.0) * (v + 2.0 * v2 + 2.0 * v3 + v4)
        v_new = v + (dt / 6.0) * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
        return _finish(scene, state, x_new, v_new, dt)


# Dormand & Prince (1980) 5(4) tableau: nodes, stage coefficients, 5th-order weights (= last row,
# first-same-as-last) and the difference between the 5th- and embedded 4th-order weights.
_DP_C = np.array([0.0, 1 / 5, 3 / 10, 4 / 5, 8 / 9, 1.0, 1.0])
_DP_A = (
    (),
    (1 / 5,),
    (3 / 40, 9 / 40),
    (44 / 45, -56 / 15, 32 / 9),
    (19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729),
    (9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656),
    (35 / 384, 0.0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84),
)
_DP_E = np.array([71 / 57600, 0.0, -71 / 16695, 71 / 1920, -17253 / 339200, 22 / 525, -1 / 40])


def _same_tree(a: Any, b: Any) -> bool:
    """Whether two friction states are equal (dataclasses, tuples, arrays, scalars); False when
    unsure."""
    if a is b:
        return True
    if type(a) is not type(b):
        return False
    if isinstance(a, np.ndarray):
        return a.shape == b.shape and bool(np.array_equal(a, b))
    if isinstance(a, (tuple, list)):
        return len(a) == len(b) and all(_same_tree(p, q) for p, q in zip(a, b, strict=True))
    if dataclasses.is_dataclass(a) and not isinstance(a, type):
        return all(_same_tree(getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a))
    if isinstance(a, (int, float, complex, str, bool, type(None))):
        return bool(a == b)
    return False


class DormandPrince45(Integrator):
    """Adaptive Dormand-Prince 5(4) with first-same-as-last and error control.

    The error of a step is the difference of the fifth- and embedded fourth-order solutions,
    measured in the RMS norm ``sqrt(mean((e_k / s_k)^2))`` with
    ``s_k = atol + rtol max(|y_k(t)|, |y_k(t + dt)|)`` (``atol_x`` [m] for positions, ``atol_v``
    [m/s] for velocities). A step is accepted when the norm is <= 1; the next step is
    ``dt * clip(safety * err^(-1/5), fac_min, fac_max)`` (no growth right after a rejection),
    capped at ``dt_max`` and at the stable bound :func:`stable_time_step` (the problem is stiff:
    the highest node frequencies bound the step long before the error does).

    Attributes
    ----------
    accepted, rejected: step counts.
    dt_next: step size [s] proposed for the next step (None before the first).
    """

    method = "dopri"
    adaptive = True

    def __init__(
        self,
        rtol: float = 1e-6,
        atol_x: float = 1e-9,
        atol_v: float = 1e-6,
        *,
        dt_max: float | None = None,
        dt_min: float = 1e-12,
        safety: float = 0.9,
        fac_min: float = 0.2,
        fac_max: float = 5.0,
        max_rejections: int = 50,
    ) -> None:
        if not (rtol >= 0 and atol_x >= 0 and atol_v >= 0 and rtol + atol_x > 0 and rtol + atol_v > 0):
            raise ValueError("tolerances must be >= 0 and rtol + atol > 0")
        if not (0 < safety <= 1 and 0 < fac_min < 1 < fac_max):
            raise ValueError("need 0 < safety <= 1 and 0 < fac_min < 1 < fac_max")
        self.rtol, self.atol_x, self.atol_v = float(rtol), float(atol_x), float(atol_v)
        self.dt_max = dt_max
        self.dt_min = float(dt_min)
        self.safety, self.fac_min, self.fac_max = float(safety), float(fac_min), float(fac_max)
        self.max_rejections = int(max_rejections)
        self.accepted = 0
        self.rejected = 0
        self.dt_next: float | None = None
        self._cap: tuple[Scene, float] | None = None
        self._fsal: tuple[State, Array] | None = None

    def stable_cap(self, scene: Scene) -> float:
        """Largest step [s] this integrator takes on ``scene``: min(dt_max, stable bound)."""
        if self._cap is None or self._cap[0] is not scene:
            self._cap = (scene, stable_time_step(scene, self.method))
        cap = self._cap[1]
        return cap if self.dt_max is None else min(cap, self.dt_max)

    def _rhs(self, scene: Scene, y: Array, t: float, contacts: tuple[Any, ...]) -> Array:
        n = y.shape[0] // 2
        x, v = y[:n], y[n:]
        return np.concatenate([v, _acceleration(scene, x, v, t, contacts)])

    def _attempt(self, scene: Scene, y: Array, k1: Array, t: float, h: float, c: tuple[Any, ...]):
        """One trial step: (y_new, f(y_new), error norm)."""
        ks = [k1]
        for i in range(1, 7):
            yi = y + h * sum(a * k for a, k in zip(_DP_A[i], ks, strict=True) if a != 0.0)
            ks.append(self._rhs(scene, yi, t + _DP_C[i] * h, c))
        y_new = yi  # stage 7 is evaluated at the fifth-order solution (FSAL)
        err = h * sum(e * k for e, k in zip(_DP_E, ks, strict=True) if e != 0.0)
        n = y.shape[0] // 2
        atol = np.empty((y.shape[0], 1))
        atol[:n], atol[n:] = self.atol_x, self.atol_v
        scale = atol + self.rtol * np.maximum(np.abs(y), np.abs(y_new))
        norm = float(np.sqrt(np.mean((err / scale) ** 2)))
        return y_new, ks[-1], norm

    def step(self, scene: Scene, state: State, dt: float) -> State:
        """Take one accepted step of at most ``dt`` [s] (and at most the stable cap).

        Raises
        ------
        SimulationUnstable
            The error test keeps failing (step below ``dt_min`` or ``max_rejections`` retries).
        """
        cap = self.stable_cap(scene)
        h = min(dt, cap)
        y = np.concatenate([state.x, state.v])
        if self._fsal is not None and self._fsal[0] is state:
            k1 = self._fsal[1]
        else:
            k1 = self._rhs(scene, y, state.t, state.contacts)
        rejected_here = 0
        while True:
            y_new, k_last, norm = self._attempt(scene, y, k1, state.t, h, state.contacts)
            if norm <= 1.0:
                break
            self.rejected += 1
            rejected_here += 1
            factor = self.safety * norm**-0.2 if math.isfinite(norm) else self.fac_min
            h *= min(1.0, max(self.fac_min, factor))
            if h < self.dt_min or rejected_here > self.max_rejections:
                raise unstable_error(
                    scene,
                    self.method,
                    state.t,
                    h,
                    f"error control failed after {rejected_here} rejected steps",
                )
        self.accepted += 1
        growth = self.safety * norm**-0.2 if norm > 0 else self.fac_max
        growth = min(self.fac_max if rejected_here == 0 else 1.0, max(self.fac_min, growth))
        self.dt_next = min(h * growth, cap)
        n = state.x.shape[0]
        new = _finish(scene, state, y_new[:n], y_new[n:], h)
        # First same as last: reuse f(y_new) if the contact update changed nothing.
        self._fsal = (new, k_last) if _same_tree(new.contacts, state.contacts) else None
        return new


def make_integrator(method: str | Integrator, **options: Any) -> Integrator:
    """An integrator from a method name (see :func:`canonical_method`) or the instance itself.

    ``options`` go to :class:`DormandPrince45` (``rtol``, ``atol_x``, ``atol_v``, ...).
    """
    if isinstance(method, Integrator):
        if options:
            raise ValueError("integrator options only apply when the method is given by name")
        return method
    name = canonical_method(method)
    if name == "dopri":
        return DormandPrince45(**options)
    if options:
        raise ValueError(f"method {name!r} takes no options, got {sorted(options)}")
    return RK4() if name == "rk4" else SemiImplicitEuler()
