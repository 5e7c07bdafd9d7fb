"""Stable time steps of the explicit integrators and detection of numerical blow-up.

Time step
---------
An explicit method applied to ``y' = lambda y`` is stable while ``lambda dt`` lies in its stability
region. For the mass-spring body linearised about rest, ``M x'' + C x' + K x = 0`` with lumped
(diagonal) M, ``K = -d f / d x`` and ``C = -d f / d v``. Gershgorin's theorem bounds the spectrum of
``M^-1 K`` by the largest scaled absolute row sum,

    omega_max^2 <= max_i (1 / m_i) sum_j |K_ij| = max_i (2 / m_i) sum_j k_ij        (Gershgorin)

(the second form for a network of springs k_ij, up to the direction cosines of the 3x3 spring
blocks: the diagonal block of a node is minus the sum of its off-diagonal blocks). Treating every
node as a scalar damped oscillator ``m_i s^2 + c_i s + k_i = 0`` with the Gershgorin row sums
k_i, c_i of K and C, every root obeys

    |s| <= rho_i = c_i / (2 m_i) + sqrt((c_i / (2 m_i))^2 + k_i / m_i).

For the whole body, an eigenpair ``(s, u)`` of ``s^2 M + s C + K`` solves the scalar quadratic
``s^2 m_u + s c_u + k_u = 0`` with the Rayleigh quotients ``m_u = u* M u`` etc., and Gershgorin
bounds ``k_u / m_u <= omega_G^2 = max_i k_i / m_i`` and ``c_u / m_u <= 2 a_G = max_i c_i / m_i``.
Hence the spectral radius of the first-order system is at most

    rho = a_G + sqrt(a_G^2 + omega_G^2) >= max_i rho_i,

which is what :func:`max_frequency` returns; it equals ``max_i rho_i`` whenever one node has both
the largest k/m and the largest c/m (so far always the case: edge dashpots are stiffness
proportional and contact dashpots grow with the contact stiffness). It overestimates the largest
undamped frequency by about 1.5x on the BCC boxes, and the damped spectral radius by up to 4x
(measured with damping ratio 0.5 on small boxes: the node bound adds rather than combines). A method
is then stable for ``dt < limit / rho``, where ``limit`` is the radius of the largest half-disc
``{|z| < limit, Re z <= 0}`` inside its stability region:

* RK4: the region reaches 2.785 on the negative real axis and 2.828 on the imaginary axis, and
  its boundary comes closest to the origin at radius 2.62 (near 123 degrees), so the classical
  criterion ``dt < 2.8 / omega_max`` holds for undamped bodies and ``limit = 2.5`` is safe for any
  damping.
* Dormand-Prince 5(4): 3.31 on the real axis and above 2.6 for any direction at least 5 degrees
  into the left half-plane, but its propagated fifth-order solution is weakly unstable on the
  imaginary axis itself (``|R(iy)| - 1`` is 1e-6 at y = 1 and 3 % at y = 2). The step is capped at
  ``2.5 / rho`` and the error controller keeps lightly damped high-frequency modes in check.
* Semi-implicit (symplectic) Euler on ``m x'' + c x' + k x = 0`` (damping evaluated with the old
  velocity): the amplification matrix has determinant ``1 - 2 z w`` and trace ``2 - w^2 - 2 z w``
  with ``w = omega dt`` and damping ratio z, and Jury's conditions give
  ``w < 2 (sqrt(1 + z^2) - z)``. Since ``rho_i = omega_i (z_i + sqrt(1 + z_i^2))`` this is exactly
  ``dt < 2 / rho_i``, so ``limit = 2``.

The bound uses the stiffness at rest. Strongly stiffening laws, the volume barrier of compressed
tets and deep contact penetration raise the stiffness beyond it; the default safety factor 0.9 and
the blow-up monitor cover moderate cases.

Blow-up detection
-----------------
:class:`BlowupMonitor` watches a trajectory and raises :class:`~softgrasp.errors.SimulationUnstable`
(with a suggested step of half the stable bound) when positions or velocities stop being finite,
when a tet inverts, or when the body's mechanical energy exceeds its energy balance by far (see
:class:`BlowupMonitor` for the balance used, which stays valid in free fall and when plates push).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from softgrasp.errors import SimulationUnstable
from softgrasp.model.mesh.tetmesh import signed_volumes
from softgrasp.sim.scene import Scene, State

__all__ = [
    "DEFAULT_SAFETY",
    "STABILITY_LIMITS",
    "BlowupMonitor",
    "EnergyBalance",
    "canonical_method",
    "half_disc_radius",
    "max_frequency",
    "node_frequency_bounds",
    "node_gershgorin",
    "stable_time_step",
    "unstable_error",
]

#: ``dt * rho`` below which each method is stable (see the module docstring).
STABILITY_LIMITS: dict[str, float] = {"rk4": 2.5, "dopri": 2.5, "semi-implicit": 2.0}
#: Fraction of the stability limit used by default.
DEFAULT_SAFETY = 0.9

_ALIASES = {
    "rk4": "rk4",
    "rk45": "dopri",
    "dopri": "dopri",
    "dopri5": "dopri",
    "dormand-prince": "dopri",
    "semi-implicit": "semi-implicit",
    "semi-implicit-euler": "semi-implicit",
    "symplectic-euler": "semi-implicit",
    "euler-cromer": "semi-implicit",
}


def canonical_method(method: str) -> str:
    """The canonical name (``rk4``, ``dopri`` or ``semi-implicit``) of an integration method.

    Accepted aliases: ``rk45``, ``dopri5``, ``dormand-prince``; ``semi-implicit-euler``,
    ``symplectic-euler``, ``euler-cromer`` (case and ``_`` versus ``-`` are ignored).

    Raises
    ------
    ValueError
        Unknown method.
    """
    key = str(method).strip().lower().replace("_", "-")
    try:
        return _ALIASES[key]
    except KeyError:
        raise ValueError(f"unknown integration method {method!r}; choose one of {sorted(_ALIASES)}") from None


def node_gershgorin(scene: Scene) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Gershgorin stiffness and damping of every node at rest.

    Returns
    -------
    k: largest absolute row sum of the node's 3 rows of the rest stiffness [N/m], (N,), plus the
        interactions' :meth:`stiffness_bound`.
    c: the same for the damping matrix at rest [N s/m], (N,), plus the interactions'
        :meth:`damping_bound`.
    """
    body = scene.body
    k, c = (a.copy() for a in body.rest_row_sums)  # computed once per body (Body.rest_row_sums)
    for inter in scene.interactions:
        k = k + np.asarray(inter.stiffness_bound(body), dtype=np.float64)
        c = c + np.asarray(inter.damping_bound(body), dtype=np.float64)
    return k, c


def node_frequency_bounds(scene: Scene) -> NDArray[np.float64]:
    """Per-node bound rho_i [rad/s] on the magnitude of the linearised eigenvalues, (N,).

    ``rho_i = c_i / (2 m_i) + sqrt((c_i / (2 m_i))^2 + k_i / m_i)`` with k_i, c_i from
    :func:`node_gershgorin` and the lumped mass m_i.
    """
    k, c = node_gershgorin(scene)
    m = scene.body.mass
    a = c / (2.0 * m)
    return a + np.sqrt(a * a + k / m)


def max_frequency(scene: Scene) -> float:
    """Upper bound rho [rad/s] on the largest angular frequency (spectral radius) of the scene.

    ``rho = a_G + sqrt(a_G^2 + omega_G^2)`` with ``a_G = max_i c_i / (2 m_i)`` and
    ``omega_G^2 = max_i k_i / m_i`` (k_i, c_i from :func:`node_gershgorin`); it is at least
    ``max_i rho_i`` of :func:`node_frequency_bounds` and usually equal to it. Without damping it is
    the Gershgorin bound ``omega_max <= sqrt(max_i (1 / m_i) sum_j |K_ij|)``.
    """
    k, c = node_gershgorin(scene)
    m = scene.body.mass
    a = float(np.max(c / (2.0 * m)))
    return a + math.sqrt(a * a + float(np.max(k / m)))


def stable_time_step(scene: Scene, method: str = "rk4", *, safety: float = DEFAULT_SAFETY) -> float:
    """Largest time step [s] an explicit method can take on ``scene``: ``safety * limit / rho``.

    Parameters
    ----------
    scene:
        Body and interactions (their stiffness and damping bounds enter rho).
    method:
        ``rk4`` (limit 2.5), ``dopri``/``rk45`` (2.5), ``semi-implicit`` (2.0); see the module
        docstring. Undamped RK4 would allow ``dt < 2.8 / omega_max``.
    safety:
        Factor in (0, 1] applied to the limit.

    Returns
    -------
    float
        The time step [s].
    """
    if not (0.0 < safety <= 1.0):
        raise ValueError(f"safety factor must lie in (0, 1], got {safety}")
    limit = STABILITY_LIMITS[canonical_method(method)]
    return safety * limit / max_frequency(scene)


def unstable_error(scene: Scene, method: str, t: float, dt: float, reason: str) -> SimulationUnstable:
    """The :class:`SimulationUnstable` to raise at time ``t`` [s] after steps of ``dt`` [s].

    The suggested step is half the stable bound of ``method`` for the scene.
    """
    try:
        suggested: float | None = 0.5 * stable_time_step(scene, method)
    except (ValueError, FloatingPointError, ZeroDivisionError):  # pragma: no cover - degenerate scene
        suggested = None
    hint = f"; use dt <= {suggested:.3g} s" if suggested is not None else ""
    return SimulationUnstable(
        f"simulation unstable at t = {t:.6g} s with dt = {dt:.3g} s ({reason}){hint}", suggested
    )


@dataclass
class EnergyBalance:
    """Running energy bookkeeping of :class:`BlowupMonitor`.

    Attributes
    ----------
    t: time of the last accounted state [s].  power: interaction power there [W].
    work: trapezoidal integral of the interaction power [J].  abs_work: the same of its magnitude [J].
    gravity_work: largest ``|m g . (x_com(t) - x_com(0))|`` so far [J].
    """

    t: float
    power: float
    work: float = 0.0
    abs_work: float = 0.0
    gravity_work: float = 0.0


class BlowupMonitor:
    """Raise :class:`SimulationUnstable` when a trajectory blows up.

    Checks, in order:

    1. every step (cheap): positions and velocities finite;
    2. every ``check_every`` steps: every tet has positive signed volume;
    3. every ``check_every`` steps: the energy balance of the body.

    The energy test uses the body's own mechanical energy
    ``E_b = kinetic + elastic + gravitational`` and the work ``W`` done on the body by the
    interactions, ``W = integral of sum_i f_i · v_i dt`` (trapezoidal rule over every accepted
    step). Physically ``E_b(t) - E_b(0) - W(t) = -(energy dissipated by the body's dampers) <= 0``,
    whatever the plates and fingers do, and in free fall gravity only converts potential into
    kinetic energy. The test fails when this excess exceeds ``energy_factor`` times the scale

        S = max(E_0, m g L, max_t |m g · (x_com(t) - x_com(0))|, integral of |sum_i f_i · v_i| dt,
                1e-10 E V),

    with ``E_0`` the initial kinetic + elastic + contact energy, L the body's largest extent and
    ``E V`` the Young's modulus times the rest volume (a floor for bodies starting at rest).
    An unstable explicit integration creates energy exponentially fast, so it trips this test well
    before positions overflow.

    Parameters
    ----------
    scene, state:
        The scene and the initial state of the trajectory.
    method:
        Integration method (for the suggested time step in the error).
    check_every:
        Steps between the volume and energy checks (>= 1).
    energy_factor:
        Allowed energy excess as a multiple of the scale S.
    """

    def __init__(
        self,
        scene: Scene,
        state: State,
        method: str = "rk4",
        *,
        check_every: int = 10,
        energy_factor: float = 10.0,
    ) -> None:
        if check_every < 1:
            raise ValueError(f"check_every must be >= 1, got {check_every}")
        self.scene = scene
        self.method = canonical_method(method)
        self.check_every = int(check_every)
        self.energy_factor = float(energy_factor)
        self.steps = 0
        body = scene.body
        self._com0 = self._com(state.x)
        self._energy0 = self._body_energy(state.x, state.v)
        e_contact = sum(
            inter.energy(body, state.x, state.t, st)
            for inter, st in zip(scene.interactions, state.contacts, strict=True)
        )
        e_static = scene.kinetic_energy(state.v) + body.internal_energy(state.x) + float(e_contact)
        g = float(np.linalg.norm(body.gravity))
        extent = float(np.ptp(np.asarray(body.mesh.points), axis=0).max())
        self._scale0 = max(
            abs(e_static), body.total_mass * g * extent, 1e-10 * body.material.E * body.mesh.volume
        )
        self._balance = EnergyBalance(t=state.t, power=self._power(state))

    # ------------------------------------------------------------------ pieces
    def _com(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        m = self.scene.body.mass
        return (m @ x) / m.sum()

    def _body_energy(self, x: NDArray[np.float64], v: NDArray[np.float64]) -> float:
        body = self.scene.body
        return self.scene.kinetic_energy(v) + body.internal_energy(x) - float(body.mass @ (x @ body.gravity))

    def _power(self, state: State) -> float:
        """Power [W] of the interaction forces on the body."""
        body = self.scene.body
        p = 0.0
        for inter, st in zip(self.scene.interactions, state.contacts, strict=True):
            f = inter.forces(body, state.x, state.v, state.t, st)
            p += float(np.einsum("ij,ij->", f, state.v))
        return p

    def _fail(self, state: State, dt: float, reason: str) -> SimulationUnstable:
        return self.error(state.t, dt, reason)

    # ------------------------------------------------------------------ for compiled loops
    @property
    def balance(self) -> EnergyBalance:
        """The running energy bookkeeping (a compiled stepper updates it in place)."""
        return self._balance

    @property
    def energy0(self) -> float:
        """Body energy ``E_b(0)`` [J] of the initial state."""
        return self._energy0

    @property
    def scale0(self) -> float:
        """The energy scale's floor [J] (initial energy, ``m g L``, ``1e-10 E V``)."""
        return self._scale0

    @property
    def com0(self) -> NDArray[np.float64]:
        """Initial centre of mass [m], (3,)."""
        return self._com0

    def error(self, t: float, dt: float, reason: str) -> SimulationUnstable:
        """The :class:`SimulationUnstable` for a failed check at time ``t`` [s] after a step of
        ``dt`` [s]."""
        return unstable_error(self.scene, self.method, t, dt, reason)

    @staticmethod
    def inverted_reason(count: int, first: int) -> str:
        """Reason text for ``count`` inverted tets, the first being ``first``."""
        more = f" and {count - 1} more" if count > 1 else ""
        return f"tet {first}{more} inverted"

    def energy_reason(self, excess: float, scale: float) -> str:
        """Reason text for an energy excess [J] above ``energy_factor`` times ``scale`` [J]."""
        return f"energy grew by {excess:.3g} J, more than {self.energy_factor:g} x {scale:.3g} J"

    # ------------------------------------------------------------------ checks
    def check_finite(self, state: State, dt: float) -> None:
        """Raise unless every position and velocity is finite."""
        if not (np.isfinite(state.x).all() and np.isfinite(state.v).all()):
            raise self._fail(state, dt, "positions or velocities became non-finite")

    def check_volumes(self, state: State, dt: float) -> None:
        """Raise if a tet has non-positive signed volume (inverted or flat)."""
        vol = signed_volumes(state.x, self.scene.body.mesh.tets)
        bad = np.flatnonzero(vol <= 0.0)
        if bad.size:
            raise self._fail(state, dt, self.inverted_reason(int(bad.size), int(bad[0])))

    def energy_excess(self, state: State) -> tuple[float, float]:
        """``(E_b(t) - E_b(0) - W(t), S)`` [J] of the energy test (see the class docstring)."""
        b = self._balance
        scale = max(self._scale0, b.abs_work, b.gravity_work)
        return self._body_energy(state.x, state.v) - self._energy0 - b.work, scale

    def check_energy(self, state: State, dt: float) -> None:
        """Raise if the energy excess is above ``energy_factor`` times its scale."""
        excess, scale = self.energy_excess(state)
        if not (excess <= self.energy_factor * scale):
            raise self._fail(state, dt, self.energy_reason(excess, scale))

    def check(self, state: State, dt: float) -> None:
        """All checks now: finite, volumes, energy."""
        self.check_finite(state, dt)
        self.check_volumes(state, dt)
        self.check_energy(state, dt)

    def after_step(self, state: State, dt: float) -> None:
        """Account for one accepted step ending in ``state`` (of length ``dt`` [s]) and check it."""
        self.check_finite(state, dt)
        self.steps += 1
        b = self._balance
        p = self._power(state)
        h = state.t - b.t
        b.work += 0.5 * (b.power + p) * h
        b.abs_work += 0.5 * (abs(b.power) + abs(p)) * h
        b.power, b.t = p, state.t
        body = self.scene.body
        dz = float((self._com(state.x) - self._com0) @ body.gravity) * body.total_mass
        b.gravity_work = max(b.gravity_work, abs(dz))
        if self.steps % self.check_every == 0:
            self.check_volumes(state, dt)
            self.check_energy(state, dt)


def half_disc_radius(coeffs: list[float], n_angles: int = 181) -> float:
    """Radius of the largest half-disc ``{|z| < r, Re z <= 0}`` inside ``{|R(z)| <= 1}``, where
    ``R(z) = sum_k coeffs[k] z^k`` is the stability polynomial of an explicit Runge-Kutta method.

    Sampled on ``n_angles`` rays and a radial grid of step 1e-3; documents (and lets tests check)
    where :data:`STABILITY_LIMITS` come from, e.g. 2.62 for RK4 ``(1, 1, 1/2, 1/6, 1/24)``.
    """
    best = math.inf
    r = np.linspace(1e-3, 6.0, 6000)
    for th in np.linspace(math.pi / 2, math.pi, n_angles):
        z = r * np.exp(1j * th)
        R = np.polyval(list(reversed(coeffs)), z)
        out = np.flatnonzero(np.abs(R) > 1.0 + 1e-9)
        if out.size:
            best = min(best, float(r[out[0]]))
    return best
