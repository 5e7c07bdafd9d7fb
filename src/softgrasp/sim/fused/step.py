"""Fused compiled time stepping: many RK4 steps of a scene in one call, without Python between.

:class:`FusedStepper` holds a body's state with its plane and fingertip contacts in arrays;
:meth:`FusedStepper.advance` runs K steps of :class:`~softgrasp.sim.explicit.RK4` in the compiled
loop of :mod:`softgrasp.sim.fused.rk4`, each followed by the friction state updates and the
checks of :class:`softgrasp.sim.stability.BlowupMonitor`: the per-step path driven by
:func:`~softgrasp.sim.explicit.simulate`, to round-off (tested to 1e-8). The pieces:

* body forces (:mod:`softgrasp.sim.fused.body`): the kernels of
  :mod:`softgrasp.physics.forces_compiled` (polynomial laws only) on :data:`PARTS` parts of the
  elements, on Numba's threads when :attr:`FusedStepper.threads` asks for more than one;
* planes and fingertips (:mod:`softgrasp.sim.fused.contacts`): the laws of
  :mod:`softgrasp.physics.planes_compiled` and :mod:`softgrasp.physics.fingertip.compiled`;
* the blow-up monitor (:mod:`softgrasp.sim.fused.monitor`), reusing the step's own force
  evaluations: the interaction forces at a new state are the ones whose power it integrates, and
  the elastic energy and inverted tets of its checks come out of the same evaluation (every
  ``check_every`` steps). A failed check stops the loop (:attr:`FusedStepper.failure`).

The trajectory does not depend on the thread count: the parts are summed in the same order.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numba
import numpy as np
from numpy.typing import NDArray

from softgrasp.physics.fingertip.detect import corner_args
from softgrasp.physics.fingertip.laws import LAW_COLUMNS
from softgrasp.physics.forces_compiled import polynomial_coefficients
from softgrasp.sim.fused.body import packed
from softgrasp.sim.fused.contacts import max_facet_edge
from softgrasp.sim.fused.monitor import (
    F_COUNT,
    F_DT,
    F_EXCESS,
    F_FIRST,
    F_SCALE,
    F_SIZE,
    F_T,
    M_SIZE,
    STATUS_ENERGY,
    STATUS_INVERTED,
    STATUS_NONFINITE,
    STATUS_OK,
    Failure,
)
from softgrasp.sim.fused.rk4 import advance

__all__ = [
    "METHODS",
    "PARTS",
    "STATUS_ENERGY",
    "STATUS_INVERTED",
    "STATUS_NONFINITE",
    "STATUS_OK",
    "Failure",
    "FusedStepper",
    "supported",
]

Array = NDArray[np.float64]

#: Methods the fused stepper runs (names of :func:`softgrasp.sim.stability.canonical_method`).
METHODS = ("rk4",)

#: The body forces are summed from this many parts (the edges and tets split evenly), each into its
#: own buffer, computed in parallel when threads are given (:attr:`FusedStepper.threads`) and one
#: after the other otherwise: the result does not depend on the thread count.
PARTS = 2


def supported(body: Any, planes: list[Any], fingers: list[Any]) -> str | None:
    """Why the fused stepper cannot run this body and these interactions, or None when it can.

    It needs a polynomial stress-strain law
    (:func:`softgrasp.physics.forces_compiled.polynomial_coefficients`), the per-tet volume term
    and at most one fingertip interaction.
    """
    if polynomial_coefficients(body.material.law) is None:
        return f"stress-strain law {type(body.material.law).__name__} is not a polynomial"
    if getattr(body, "volume", "element") != "element":
        return f"the {body.volume} volume term (the fused kernels sum the per-tet one)"
    if len(fingers) > 1:
        return "more than one fingertip interaction"
    return None


def _f64(a: Any, shape: tuple[int, ...] | None = None) -> Array:
    """A fresh writeable C-contiguous float64 copy (one compiled signature whatever the input:
    read-only mesh arrays would make another)."""
    out = np.array(a, dtype=np.float64, order="C", copy=True)
    return out.reshape(shape) if shape is not None else out


def _i64(a: Any) -> NDArray[np.int64]:
    """A fresh writeable C-contiguous int64 copy."""
    return np.array(a, dtype=np.int64, order="C", copy=True)


def _finger_arrays(fingers: Any, body: Any) -> tuple:
    """The fingertips' constant geometry and parameters in the layout of
    :mod:`softgrasp.sim.fused.contacts` (the arguments FingertipContact's kernels get)."""
    kw = fingers._compiled_kwargs(body, 0.0)
    tips = fingers.fingertips
    nf = len(tips)
    return (
        True,
        _i64(kw["facets"]),
        _i64(kw["boundary_nodes"]),
        _i64(kw["indptr"]),
        _i64(kw["indices"]),
        float(kw["reach"]),
        _f64([f.centre for f in tips], (nf, 3)),
        _f64([f.velocity for f in tips], (nf, 3)),
        _f64([f.omega for f in tips], (nf, 3)),
        _f64(kw["radii"], (nf,)),
        _f64(kw["law"], (nf, LAW_COLUMNS)),
        _f64(fingers.damping(), (nf,)),
        bool(kw["closest"]),
        float(kw["inside_tol"]),
        float(kw["mu"]),
        float(kw["exponent"]),
        fingers.params.damping == "hunt-crossley",
        bool(kw["patch"]),
        float(kw["ratio"]),
        float(kw["min_depth_ratio"]),
        corner_args(kw["corners"]),
    )


#: The fingertip tuple of a scene without fingertips (the same compiled signature).
_NO_FINGERS = (
    False, np.zeros((1, 3), np.int64), np.zeros(1, np.int64), np.zeros(1, np.int64), np.zeros(1, np.int64),
    0.0, np.zeros((1, 3)), np.zeros((1, 3)), np.zeros((1, 3)), np.zeros(1), np.zeros((1, LAW_COLUMNS)), np.zeros(1),
    False, 0.0, 0.0, 1.0, False, False, 0.0, 0.0, corner_args(None),
)  # fmt: skip


class FusedStepper:
    """RK4 steps of a body with plane and fingertip contacts in compiled chunks.

    The stepper owns copies of the positions, velocities and friction states; :meth:`advance` moves
    them on; :meth:`arrays`, :meth:`plane_states` and :meth:`finger_state` read them out (copies).

    Parameters
    ----------
    body:
        The :class:`softgrasp.physics.body.Body` (polynomial stress-strain law).
    planes:
        :class:`softgrasp.physics.planes.PlaneContact` interactions, with their states ``plane_states``
        (:class:`~softgrasp.physics.planes.PlaneState`).
    fingers:
        A :class:`softgrasp.physics.fingertip.contact.FingertipContact` or None, with its state
        ``finger_state`` (:class:`~softgrasp.physics.fingertip.contact.FingerState`).
    x, v, t:
        Initial positions [m] (N, 3), velocities [m/s] (N, 3) and time [s].
    monitor:
        A :class:`softgrasp.sim.stability.BlowupMonitor` whose checks run inside the loop and whose
        bookkeeping (``steps``, ``balance``) is kept up to date after every :meth:`advance`; None for
        no checks.
    method:
        ``"rk4"`` (:data:`METHODS`).
    parts:
        Parts the body forces are split in (:data:`PARTS`).

    Attributes
    ----------
    threads: threads the next :meth:`advance` computes on (1: the parts one after the other).
    failure: what stopped the last :meth:`advance` early (:class:`Failure`), or None.
    """

    def __init__(
        self,
        body: Any,
        planes: list[Any],
        plane_states: list[Any],
        fingers: Any | None,
        finger_state: Any | None,
        x: Array,
        v: Array,
        t: float,
        monitor: Any | None = None,
        *,
        method: str = "rk4",
        parts: int = PARTS,
    ) -> None:
        if method not in METHODS:
            raise ValueError(f"the fused stepper runs {' or '.join(METHODS)}, not {method!r}")
        self.method = method
        reason = supported(body, planes, [] if fingers is None else [fingers])
        if reason is not None:
            raise ValueError(f"the fused stepper cannot run this scene: {reason}")
        N = body.n_nodes
        self.body = body
        self.t = float(t)
        self.x = _f64(x, (N, 3))
        self.v = _f64(v, (N, 3))
        self._body = packed(body)
        self.parts = max(1, int(parts))
        self.threads = 1
        self._mass = _f64(body.mass)
        self._grav = body.mass[:, None] * np.asarray(body.gravity, dtype=np.float64)[None, :]
        self._gvec = _f64(body.gravity, (3,))
        self._total_mass = float(body.mass.sum())
        self._have_forces = False
        # planes: (P, ...) parameter arrays and states
        P = len(planes)
        point, normal, velocity, mu = np.zeros((P, 3)), np.zeros((P, 3)), np.zeros((P, 3)), np.zeros(P)
        pk, pc, pkt, pct = (np.zeros((P, N)) for _ in range(4))
        self.pl_active = np.zeros((P, N), np.bool_)
        self.pl_anchor = np.zeros((P, N, 3))
        for p, (inter, st) in enumerate(zip(planes, plane_states, strict=True)):
            point[p], normal[p], velocity[p] = inter.plane.point, inter.plane.normal, inter.plane.velocity
            mu[p] = inter.mu
            pk[p], pc[p], pkt[p], pct[p] = inter._coeffs(body)  # PlaneContact's per-node coefficients
            self.pl_active[p] = st.active
            self.pl_anchor[p] = st.anchor
        self._pl = (point, normal, velocity, mu, pk, pc, pkt, pct)
        # fingertips: constant geometry and parameters, double-buffered state (buffer 0 holds the
        # state; entries of inactive pairs are never read and kept zero, so that a buffer can be
        # cleared through its active flags)
        if fingers is not None:
            self._fg = _finger_arrays(fingers, body)
            nf, F = len(fingers.fingertips), len(body.mesh.facets)
        else:
            self._fg = _NO_FINGERS
            nf, F = 1, 1
        self.f_active = np.zeros((2, nf, F), np.bool_)
        self.f_anchor = np.zeros((2, nf, F, 3))
        self.f_offset = np.zeros((2, nf, F, 3))
        self.f_slip = np.zeros((2, nf, F, 3))
        self.f_memory = np.zeros((2, nf, 3))
        if fingers is not None:
            st = finger_state
            act = np.asarray(st.active, dtype=np.bool_)
            self.f_active[0] = act
            self.f_anchor[0] = np.where(act[:, :, None], st.anchor, 0.0)
            self.f_offset[0] = np.where(act[:, :, None], st.offset, 0.0)
            self.f_slip[0] = np.where(act[:, :, None], st.slip, 0.0)
            self.f_memory[0] = st.memory
        self._cur = 0
        self._fstate = (self.f_active, self.f_anchor, self.f_slip, self.f_memory, self.f_offset)
        # stage positions and velocities, the weighted sums of the stage velocities and accelerations
        self._rk = tuple(np.zeros((N, 3)) for _ in range(4))
        # workspace (see softgrasp.sim.fused.rk4); the fingertip broad phase lists its near nodes at
        # the first use
        track = np.zeros(3 + 3 * nf)
        track[0] = max_facet_edge(self.x, _i64(body.mesh.facets))
        track[2] = -1.0
        self._work = (
            np.zeros((self.parts, N, 3)), np.zeros((self.parts, 3)), np.zeros((N, 3)), np.zeros((N, 3)),
            np.zeros((nf, 3)), self.x.copy(), track, np.zeros((P, 3)),
            np.zeros(max(1, len(self._fg[2])), np.int64),
        )  # fmt: skip
        self.monitor = monitor
        self._mon = np.zeros(M_SIZE)
        self._fail = np.zeros(F_SIZE)
        if monitor is not None:
            b = monitor.balance
            self._mon[:] = (
                b.t, b.power, b.work, b.abs_work, b.gravity_work,
                monitor.energy0, monitor.scale0, monitor.energy_factor, *monitor.com0,
            )  # fmt: skip
        self.failure: Failure | None = None
        self._broken = False

    def advance(self, n_steps: int, dt: float, t_end: float | None = None) -> int:
        """Take ``n_steps`` steps of ``dt`` [s] (the last one ending exactly at ``t_end`` [s] when
        given: ``t_end - t``, as :func:`softgrasp.sim.explicit.simulate` lands).

        Returns
        -------
        int
            The steps taken: ``n_steps``, or fewer when a blow-up check failed (then
            :attr:`failure` says which, and the stepper's state is that of the failed step).
        """
        if self._broken:
            raise RuntimeError(
                "this fused stepper failed in an earlier advance() and its state is undefined: make a new one"
            )
        if n_steps <= 0:
            return 0
        mon = self.monitor
        parallel = self.threads > 1 and self.parts > 1
        previous = numba.get_num_threads()
        if parallel:
            numba.set_num_threads(min(self.threads, self.parts, numba.config.NUMBA_NUM_THREADS))
        try:
            land, end = t_end is not None, float(t_end if t_end is not None else 0.0)
            status, steps, t, cur, msteps = advance(
                int(n_steps), float(dt), land, end, self.t, self.x, self.v, self._mass, self._grav,
                self._total_mass, self._body, self._pl, self.pl_active, self.pl_anchor, self._fg,
                self._fstate, self._cur, self._work, self._have_forces, parallel, mon is not None, self._mon,
                int(mon.steps if mon is not None else 0), int(mon.check_every if mon is not None else 1),
                self._gvec, self._fail, self._rk,
            )  # fmt: skip
        except BaseException:
            # positions, velocities and contact states moved on while the time and the state
            # cursor did not: refuse to go on from there
            self._broken = True
            raise
        finally:
            if parallel:
                numba.set_num_threads(previous)
        self.t = float(t)
        self._cur = int(cur)
        self._have_forces = status == STATUS_OK
        if mon is not None:
            mon.steps = int(msteps)
            b = mon.balance
            b.t, b.power, b.work, b.abs_work, b.gravity_work = (float(a) for a in self._mon[:5])
        if status != STATUS_OK:
            f = self._fail
            self.failure = Failure(
                int(status), float(f[F_T]), float(f[F_DT]), int(f[F_COUNT]), int(f[F_FIRST]),
                float(f[F_EXCESS]), float(f[F_SCALE]),
            )  # fmt: skip
        return int(steps)

    def arrays(self) -> tuple[Array, Array, float]:
        """Copies of the positions [m] and velocities [m/s] (N, 3), and the time [s]."""
        return self.x.copy(), self.v.copy(), self.t

    def plane_states(self, templates: list[Any]) -> list[Any]:
        """The planes' friction states: ``templates`` (their states at the start) with ``active``
        and ``anchor`` replaced by copies of the current ones."""
        return [
            replace(st, active=self.pl_active[p].copy(), anchor=self.pl_anchor[p].copy())
            for p, st in enumerate(templates)
        ]

    def finger_state(self, template: Any) -> Any:
        """The fingertips' contact state (``template`` with its arrays replaced by copies)."""
        c = self._cur
        return replace(
            template,
            active=self.f_active[c].copy(),
            anchor=self.f_anchor[c].copy(),
            offset=self.f_offset[c].copy(),
            slip=self.f_slip[c].copy(),
            memory=self.f_memory[c].copy(),
        )
