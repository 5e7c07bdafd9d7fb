"""Pictures of an executed grasp drawn by MuJoCo's own offscreen renderer.

:func:`open_renderer` makes a :class:`SceneRenderer` for a compiled
:class:`~softgrasp.execution.mujoco.scene.MujocoScene`: ``mujoco.Renderer`` with one fixed free
camera (:func:`frame_camera`) and an arrow per finger of its contact force on the object, so
every picture of a run is taken from the same place at the same arrow scale.
:class:`EventPictures` is the executor's ``on_event`` callback that takes a picture at each event
(``start``, ``contact``, ``closed``, ``end``), or, when no renderer could be made, the hand's
snapshot for the matplotlib pictures; :func:`event_pictures` sets both up for a hand.

Rendering without a screen needs an OpenGL back-end that makes a context without one: on Linux
MuJoCo's ``egl`` (Mesa's EGL: Debian's :data:`GL_PACKAGES`), chosen by the ``MUJOCO_GL`` variable
that MuJoCo reads when it is first imported:
:func:`~softgrasp.offscreen.prefer_headless_gl` sets it to ``egl`` where the user has
not chosen one. When ``mujoco.Renderer`` cannot be made (no GL library, no device),
:func:`open_renderer` warns (:class:`~softgrasp.errors.SoftgraspWarning`, one line naming the
packages) and returns None: the pictures are then drawn by matplotlib from the snapshots.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from softgrasp.errors import SoftgraspWarning
from softgrasp.execution.mujoco.hand import MujocoHand
from softgrasp.execution.mujoco.scene import MujocoScene, import_mujoco
from softgrasp.offscreen import GL_BACKEND

__all__ = [
    "FRAME_HEIGHT",
    "FRAME_WIDTH",
    "GL_PACKAGES",
    "EventPictures",
    "FrameCamera",
    "SceneRenderer",
    "event_pictures",
    "frame_camera",
    "open_renderer",
]

#: Debian's packages behind MuJoCo's ``egl`` back-end (``make install`` installs them where it can).
GL_PACKAGES = ("libegl1", "libegl-mesa0", "libgl1-mesa-dri")
#: Size of a picture [pixels].
FRAME_WIDTH, FRAME_HEIGHT = 640, 480
#: Elevation of the camera [deg] (negative: looking down on the table).
CAMERA_ELEVATION = -20.0
#: The camera's distance over the least that keeps the scene's bounding sphere in the picture.
FRAME_MARGIN = 1.15
#: Length [m] of the arrow of the largest set-point, as a fraction of the object's size.
ARROW_FRACTION = 0.6
#: The scene's light the camera looks along (it shows the object's lit side).
KEY_LIGHT = "key"
#: RGBA of the force arrow of finger i (thumb, first, middle, then more; cycled).
ARROW_COLOURS = ((1.0, 0.85, 0.1, 1.0), (0.2, 0.55, 1.0, 1.0), (0.2, 0.85, 0.35, 1.0), (0.8, 0.3, 0.9, 1.0))


class FrameCamera(NamedTuple):
    """MuJoCo's free camera of a run's pictures (``mujoco.MjvCamera``).

    Attributes
    ----------
    lookat: the point looked at [m], world frame, (3,).  distance: from it [m].
    azimuth: [deg] about the world z axis.  elevation: [deg], negative looking down.
    """

    lookat: NDArray[np.float64]
    distance: float
    azimuth: float
    elevation: float


def frame_camera(
    points: NDArray[np.float64],
    tips: NDArray[np.float64],
    hand: NDArray[np.float64],
    lift_m: float,
    *,
    light_dir: NDArray[np.float64] | None = None,
    fovy_deg: float = 45.0,
) -> FrameCamera:
    """The one camera of a run. It looks at the object's initial centroid raised by half the
    lift, from the side across the line from the thumb (first fingertip) to the other fingertips'
    mean (every fingertip in view), on the side the key light comes from, :data:`CAMERA_ELEVATION`
    from above, from far enough that the object, the hand and both lifted by ``lift_m`` fit in the
    picture.

    points: the object's nodes at the start [m], (N, 3).  tips: fingertip centres at the start
    [m], (F, 3), the thumb first.  hand: points of the hand at the start [m], (K, 3) (palm,
    knuckles).  lift_m: the lift height [m].  light_dir: the key light's direction (3,) (towards
    what it lights).  fovy_deg: the camera's vertical field of view.
    """
    pts = np.asarray(points, dtype=np.float64)
    tip = np.asarray(tips, dtype=np.float64).reshape(-1, 3)
    centroid = pts.mean(axis=0)
    across = tip[0] - tip[1:].mean(axis=0) if len(tip) > 1 else tip[0] - centroid
    look = np.array([-across[1], across[0], 0.0])  # horizontal, normal to the grasp's line
    if float(np.linalg.norm(look)) < 1e-9:
        look = np.array([1.0, 0.0, 0.0])
    if light_dir is not None and float(np.dot(look[:2], np.asarray(light_dir, dtype=np.float64)[:2])) < 0:
        look = -look  # the camera on the lit side: it looks the way the light goes
    lookat = centroid + np.array([0.0, 0.0, 0.5 * lift_m])
    shown = np.vstack([pts, tip, np.asarray(hand, dtype=np.float64).reshape(-1, 3)])
    shown = np.vstack([shown, shown + np.array([0.0, 0.0, lift_m])])
    radius = float(np.max(np.linalg.norm(shown - lookat, axis=1)))
    distance = FRAME_MARGIN * radius / math.sin(math.radians(0.5 * fovy_deg))
    azimuth = math.degrees(math.atan2(look[1], look[0]))
    return FrameCamera(lookat, float(distance), float(azimuth), CAMERA_ELEVATION)


class SceneRenderer:
    """MuJoCo's offscreen renderer of one scene with one fixed camera (made by
    :func:`open_renderer`): :meth:`capture` returns what the camera sees now."""

    def __init__(
        self,
        scene: MujocoScene,
        camera: FrameCamera,
        renderer: Any,
        fingers: Sequence[str],
        radius: float,
        force_scale: float,
    ) -> None:
        mj = import_mujoco()
        self._mj = mj
        self.scene = scene
        self.camera = camera
        self.fingers = tuple(fingers)
        self.radius = float(radius)
        self.force_scale = float(force_scale)
        self._renderer = renderer
        self._cam = mj.MjvCamera()
        self._cam.type = mj.mjtCamera.mjCAMERA_FREE
        self._cam.lookat[:] = camera.lookat
        self._cam.distance = camera.distance
        self._cam.azimuth = camera.azimuth
        self._cam.elevation = camera.elevation
        # the flex's faces, flat-shaded: its smooth skin comes out dark (normals facing inwards)
        self._option = mj.MjvOption()
        self._option.flags[mj.mjtVisFlag.mjVIS_FLEXSKIN] = False
        self._option.flags[mj.mjtVisFlag.mjVIS_FLEXFACE] = True

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) of a picture [pixels]."""
        return int(self._renderer.width), int(self._renderer.height)

    def capture(self) -> NDArray[np.uint8]:
        """The scene now, seen by the camera, with an arrow per finger of its contact force on the
        object (its head on the fingertip's back, pushing it; :attr:`force_scale` [m/N] long):
        RGB, (height, width, 3)."""
        self.scene.forward()
        self._renderer.update_scene(self.scene.data, self._cam, self._option)
        for i, finger in enumerate(self.fingers):
            force = self.scene.fingertip_force(finger)
            norm = float(np.linalg.norm(force))
            if norm * self.force_scale < 0.2 * self.radius:  # no contact, or too small to draw
                continue
            unit = force / norm
            head = self.scene.fingertip_position(finger) - self.radius * unit  # behind the fingertip
            self._arrow(head - self.force_scale * force, head, ARROW_COLOURS[i % len(ARROW_COLOURS)])
        return np.array(self._renderer.render(), dtype=np.uint8)

    def _arrow(self, tail: NDArray[np.float64], head: NDArray[np.float64], rgba: Sequence[float]) -> None:
        """Add an arrow from ``tail`` to ``head`` [m] to the renderer's scene of this picture."""
        mj, scn = self._mj, self._renderer.scene
        if scn.ngeom >= scn.maxgeom:
            return
        geom = scn.geoms[scn.ngeom]
        mj.mjv_initGeom(
            geom,
            mj.mjtGeom.mjGEOM_ARROW,
            np.zeros(3),
            np.zeros(3),
            np.eye(3).ravel(),
            np.asarray(rgba, np.float32),
        )
        # MuJoCo draws a connector arrow half as long as the span it is given (measured, 4.0)
        mj.mjv_connector(geom, mj.mjtGeom.mjGEOM_ARROW, 0.3 * self.radius, tail, 2.0 * head - tail)
        scn.ngeom += 1

    def close(self) -> None:
        """Free the renderer's OpenGL context."""
        close = getattr(self._renderer, "close", None)
        if close is not None:
            close()


def open_renderer(
    scene: MujocoScene,
    camera: FrameCamera,
    fingers: Sequence[str],
    radius: float,
    *,
    largest_force_N: float,
    size: float,
    width: int = FRAME_WIDTH,
    height: int = FRAME_HEIGHT,
    make: Callable[[Any, int, int], Any] | None = None,
) -> SceneRenderer | None:
    """MuJoCo's offscreen renderer of ``scene`` seen by ``camera`` with the contact force of each
    of ``fingers`` (fingertip spheres of ``radius`` [m]) as an arrow, scaled so that
    ``largest_force_N`` [N] is :data:`ARROW_FRACTION` of ``size`` [m] long; None, with a
    :class:`~softgrasp.errors.SoftgraspWarning` naming :data:`GL_PACKAGES`, when it cannot be made.

    make: makes the renderer from (model, height, width); default ``mujoco.Renderer``.
    """
    make = import_mujoco().Renderer if make is None else make
    try:
        with warnings.catch_warnings():  # GLFW's own warnings on a machine without a screen
            warnings.simplefilter("ignore")
            renderer = make(scene.model, height, width)
    except Exception as exc:  # no OpenGL library, no device, a context MuJoCo cannot make
        reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        warnings.warn(
            f"MuJoCo's offscreen renderer could not start ({reason}): the execution pictures are drawn "
            f"by matplotlib instead; install Debian's {' '.join(GL_PACKAGES)} (make install does, as "
            f"root) with MUJOCO_GL={GL_BACKEND} set before MuJoCo is imported",
            SoftgraspWarning,
            stacklevel=2,
        )
        return None
    scale = ARROW_FRACTION * size / max(largest_force_N, 1e-9)
    return SceneRenderer(scene, camera, renderer, fingers, radius, scale)


class EventPictures:
    """The ``on_event`` callback of :func:`~softgrasp.execution.controller.execute_plan` that keeps
    a picture of the scene at each event: ``images`` (MuJoCo's, when ``renderer`` is given) or
    ``snapshots`` (:meth:`MujocoHand.snapshot`, for matplotlib), and ``times`` [s] of each."""

    def __init__(self, hand: MujocoHand, names: Sequence[str], renderer: SceneRenderer | None) -> None:
        self.hand = hand
        self.names = tuple(names)
        self.renderer = renderer
        self.images: dict[str, NDArray[np.uint8]] = {}
        self.snapshots: dict[str, tuple] = {}
        self.times: dict[str, float] = {}

    def __call__(self, event: str) -> None:
        self.times[event] = self.hand.time
        if self.renderer is not None:
            self.images[event] = self.renderer.capture()
        else:
            self.snapshots[event] = self.hand.snapshot(self.names)

    def close(self) -> None:
        """Free the renderer (the pictures stay)."""
        if self.renderer is not None:
            self.renderer.close()
            self.renderer = None


def event_pictures(
    hand: MujocoHand,
    radius: float,
    lift_m: float,
    largest_force_N: float,
    *,
    make: Callable[[Any, int, int], Any] | None = None,
) -> EventPictures:
    """The pictures of an execution on ``hand`` (fingertip spheres of ``radius`` [m], a lift of
    ``lift_m`` [m], force arrows scaled to ``largest_force_N`` [N]; :func:`open_renderer`), from
    the one camera :func:`frame_camera` places at the scene's start; matplotlib's snapshots when no
    renderer can be made (``make``: see :func:`open_renderer`)."""
    scene, names = hand.scene, hand.fingers
    scene.forward()
    points = scene.object_nodes()
    tips = np.array([scene.fingertip_position(n) for n in names])
    mj = import_mujoco()
    key = mj.mj_name2id(scene.model, mj.mjtObj.mjOBJ_LIGHT, KEY_LIGHT)
    camera = frame_camera(
        points,
        tips,
        np.vstack(hand.links()),
        lift_m,
        light_dir=np.array(scene.model.light_dir[key]) if key >= 0 else None,
        fovy_deg=float(scene.model.vis.global_.fovy),
    )
    size = float(np.max(points.max(axis=0) - points.min(axis=0)))
    renderer = open_renderer(
        scene, camera, names, radius, largest_force_N=largest_force_N, size=size, make=make
    )
    return EventPictures(hand, names, renderer)
