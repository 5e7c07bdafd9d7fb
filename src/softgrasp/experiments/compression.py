"""Uniaxial compression between two rigid plates (paper Sec. 4.2, Figs. 8-9).

The object settles under gravity on a fixed bottom plate (:func:`softgrasp.sim.static.solve_rest`);
a top plate starting on its top moves down to the requested engineering strain in quasi-static
increments. Each increment is a static solve (:func:`softgrasp.sim.static.solve_increment`) with
gravity. The plate force is read from the top plate. Plates are frictionless by default (a
lubricated test, giving a uniaxial stress state); ``plate_friction`` > 0 sticks the faces as in an
unlubricated rig.

Stress is nominal: force over the area of the object's outline seen from above (the footprint of a
box, pi R^2 for a sphere); strain is the plate travel over the initial height, positive in
compression as in test reports.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import ConvexHull

from softgrasp.errors import ConfigError, NotConverged
from softgrasp.linalg.solve import SolverCache
from softgrasp.physics.body import Body
from softgrasp.physics.planes import Plane, PlaneContact
from softgrasp.physics.supports import Tether
from softgrasp.sim.scene import Scene
from softgrasp.sim.static import extrapolated, solve_increment, solve_rest

__all__ = ["CompressionResult", "compression_test", "outline_area"]


@dataclass(frozen=True)
class CompressionResult:
    """Force-displacement record of a compression test.

    Attributes
    ----------
    displacement_m: top plate travel [m], (K,), starting at 0.
    force_N: force of the top plate on the object [N], (K,).
    bottom_force_N: force of the bottom plate on the object [N], (K,) (= force + weight).
    strain: nominal compressive strain (displacement / height), (K,).
    stress_Pa: nominal compressive stress (force / area) [Pa], (K,).
    lateral_strain: change of the object's width along x over its initial width, (K,): the
        area-weighted mean x displacement of the boundary facets facing +x minus that of the facets
        facing -x (like an extensometer across the faces), over the initial x extent.
    height_m: initial height [m].
    area_m2: nominal area [m^2].
    apparent_E_Pa: initial slope of stress vs strain [Pa] (least squares through the origin over
        strains up to ``fit_strain``).
    apparent_nu: minus lateral strain over axial strain over the same range.
    fit_strain: largest strain used for the initial-slope fits.
    newton_iterations: Newton iterations per increment, (K,).
    tether_force_N: largest net force of the weak lateral tethers over the test [N] (~0).
    wall_time_s: wall time of the test [s].
    final_positions_m: node positions at the last increment, (N, 3).
    """

    displacement_m: NDArray[np.float64]
    force_N: NDArray[np.float64]
    bottom_force_N: NDArray[np.float64]
    strain: NDArray[np.float64]
    stress_Pa: NDArray[np.float64]
    lateral_strain: NDArray[np.float64]
    height_m: float
    area_m2: float
    apparent_E_Pa: float
    apparent_nu: float
    fit_strain: float
    newton_iterations: NDArray[np.int64]
    tether_force_N: float
    wall_time_s: float
    final_positions_m: NDArray[np.float64]


def outline_area(points: NDArray[np.float64]) -> float:
    """Area [m^2] of the convex outline of ``points`` projected on the xy plane."""
    return float(ConvexHull(points[:, :2]).volume)


def _side_weights(mesh) -> tuple[NDArray[np.float64], float]:
    """Node weights (N,) whose dot product with x displacements gives the mean x displacement of
    the +x-facing boundary minus that of the -x-facing boundary; and the initial x extent [m]."""
    nx = mesh.facet_normals[:, 0]
    w = np.zeros(mesh.n_nodes)
    for sign in (1.0, -1.0):
        sel = sign * nx > 0.9
        if not sel.any():
            raise ConfigError("the object has no boundary facing the x direction to measure its width")
        a = mesh.facet_areas[sel] / mesh.facet_areas[sel].sum()
        np.add.at(w, mesh.facets[sel].ravel(), sign * np.repeat(a / 3.0, 3))
    return w, float(np.ptp(mesh.points[:, 0]))


def _schedule(strain: float, steps: int, first: float) -> NDArray[np.float64]:
    """Strain levels: a few small ones for the initial slope, then uniform increments."""
    small = [s for s in (first, 2 * first, 4 * first) if s < strain / steps]
    return np.concatenate([[0.0], small, np.linspace(strain / steps, strain, steps)])


def _no_rest(strain: float, last: float, plate_friction: float, exc: NotConverged) -> NotConverged:
    """Why a compression stopped at ``strain`` (the last at rest: ``last``) and what to change: a
    smaller final strain, or lubricated platens (with friction, nodes of the faces flip between
    sticking and leaving the plates as the sides bulge, and the static solve can cycle there
    whatever the increments)."""
    options = f"compress to --strain {last:.3g} or less"
    if plate_friction > 0:
        options += ", or with lubricated platens (--plate-friction 0)"
    return NotConverged(
        f"the compression found no rest at {strain:.1%} strain, past {last:.1%} ({exc.diagnosis})", options
    )


def compression_test(
    body: Body,
    *,
    strain: float = 0.3,
    steps: int = 30,
    plate_friction: float = 0.0,
    penalty: float = 50.0,
    fit_strain: float = 0.01,
    progress: Callable[[float], None] | None = None,
) -> CompressionResult:
    """Compress ``body`` between rigid plates to ``strain`` and record force and displacement.

    Parameters
    ----------
    body: the object (standing anywhere; the plates are placed at its lowest and highest points).
    strain: final nominal compressive strain, in (0, 0.8].
    steps: number of uniform increments (three extra small ones come first for the initial slope).
    plate_friction: friction coefficient between plates and object (0: lubricated).
    penalty: plate contact stiffness per node relative to the node's own stiffness.
    fit_strain: largest strain used to fit the apparent modulus and Poisson ratio.
    progress: called with the completed fraction after every increment.

    Raises
    ------
    ConfigError: strain or steps out of range.
    NotConverged: an increment did not reach equilibrium (the message names the strain reached
        and what to change).
    """
    if not (0 < strain <= 0.8):
        raise ConfigError(f"compression strain = {strain} is invalid: give a value in (0, 0.8]")
    if not (1 <= steps <= 10000):
        raise ConfigError(f"steps = {steps} is invalid: give 1 to 10000 increments")
    t0 = time.perf_counter()
    x0 = np.asarray(body.mesh.points)
    zmin, zmax = float(x0[:, 2].min()), float(x0[:, 2].max())
    H = zmax - zmin
    area = outline_area(x0)
    bottom = PlaneContact(Plane([0, 0, zmin], [0, 0, 1]), mu=plate_friction, penalty=penalty, name="bottom")
    # Rigid motions the plates may leave free (sliding, spinning, tilting on single-node contacts)
    # are held by weak lateral tethers; under the symmetric load their net force vanishes.
    tether = Tether("xy")
    # Double-precision factors: the calibration differences these curves (see SolverCache.precision).
    cache = SolverCache(precision="double")
    # The object first settles under its own weight; like a rig zeroed at first contact, the top
    # plate then starts on the settled top.
    rest = Scene(body, (bottom, tether))
    settled, _ = solve_rest(rest, rest.initial_state(), cache=cache)
    ztop = float(settled.x[:, 2].max())
    top = PlaneContact(
        Plane([0, 0, ztop], [0, 0, -1], velocity=[0, 0, -1.0]), mu=plate_friction, penalty=penalty, name="top"
    )
    scene = Scene(body, (bottom, top, tether))
    levels = _schedule(strain, steps, fit_strain / 4)
    state = scene.initial_state(settled.x)
    side_w, width = _side_weights(body.mesh)
    disp, force, lat, iters, fbot = [], [], [], [], []
    tether_force = 0.0
    previous, e_prev, e_last = state, 0.0, 0.0
    for i, e in enumerate(levels):
        # Newton starts from the last two rests extrapolated to this strain.
        guess = None
        if i > 0 and e_last != e_prev:
            guess = extrapolated(state.x, previous.x, (e - e_last) / (e_last - e_prev))
        previous, e_prev, e_last = state, e_last, e
        try:
            state, its, _ = solve_increment(scene, state, e * H, cache=cache, guess=guess)
        except NotConverged as exc:
            raise _no_rest(e, e_prev, plate_friction, exc) from exc
        f = top.static_forces(body, state.x, state.t, state.contacts[1]).sum(axis=0)
        disp.append(e * H)
        force.append(float(-f[2]))
        fb = bottom.static_forces(body, state.x, state.t, state.contacts[0]).sum(axis=0)
        fbot.append(float(fb[2]))
        lat.append(float(side_w @ (state.x[:, 0] - x0[:, 0])) / width)
        tether_force = max(tether_force, float(np.abs(tether.total_force(body, state.x)).max()))
        iters.append(its)
        if progress is not None:
            progress((i + 1) / len(levels))
    d = np.array(disp)
    F = np.array(force)
    eps = d / H
    sig = F / area
    latv = np.array(lat)
    sel = (eps > 0) & (eps <= fit_strain + 1e-12)
    if not sel.any():
        sel = eps > 0
        sel[np.argmax(sel) + 1 :] = False
    E_app = float(eps[sel] @ sig[sel] / (eps[sel] @ eps[sel]))
    nu_app = float((eps[sel] @ latv[sel]) / (eps[sel] @ eps[sel]))
    return CompressionResult(
        displacement_m=d,
        force_N=F,
        bottom_force_N=np.array(fbot),
        strain=eps,
        stress_Pa=sig,
        lateral_strain=latv,
        height_m=H,
        area_m2=area,
        apparent_E_Pa=E_app,
        apparent_nu=nu_app,
        fit_strain=fit_strain,
        newton_iterations=np.array(iters),
        tether_force_N=tether_force,
        wall_time_s=time.perf_counter() - t0,
        final_positions_m=state.x,
    )
