"""Private helpers around the gmsh Python API: a quiet, deterministic session and tet extraction.

gmsh is one global C++ singleton per process, so every use goes through :func:`gmsh_session`,
which serialises callers with a lock, silences gmsh, pins the options that make meshes
reproducible (one thread, fixed random seed, fixed algorithms) and turns gmsh's exceptions into
:class:`~softgrasp.errors.MeshError`. gmsh is imported only inside these functions, so the rest of
softgrasp imports without it.
"""

from __future__ import annotations

import itertools
import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import ModuleType

import numpy as np
from numpy.typing import NDArray

from softgrasp.errors import MeshError
from softgrasp.model.mesh.tetmesh import TetMesh

__all__ = [
    "MAX_TETS",
    "TETS_PER_H3",
    "check_mesh_size",
    "compact_nodes",
    "default_mesh_size",
    "gmsh_session",
    "tet_mesh_from_model",
]

#: Largest number of tetrahedra a generator agrees to produce.
MAX_TETS = 2_000_000
#: Tets per h^3 of solid volume for a gmsh Delaunay mesh of size h (measured 4.5-5.3 on spheres
#: and cylinders at fine sizes; rounded up so the estimate errs on the large side).
TETS_PER_H3 = 6.0
#: Options pinned for every session: silent, single-threaded, fixed seed and algorithms, linear
#: elements, netgen optimisation for quality.
_OPTIONS: dict[str, float] = {
    "General.Terminal": 0,
    "General.Verbosity": 2,
    "General.NumThreads": 1,
    "Mesh.MaxNumThreads1D": 1,
    "Mesh.MaxNumThreads2D": 1,
    "Mesh.MaxNumThreads3D": 1,
    "Mesh.RandomSeed": 1,
    "Mesh.Algorithm": 6,
    "Mesh.Algorithm3D": 1,
    "Mesh.ElementOrder": 1,
    "Mesh.MeshSizeFactor": 1.0,
    "Mesh.MeshSizeFromCurvature": 0,
    "Mesh.MeshSizeFromPoints": 1,
    "Mesh.MeshSizeExtendFromBoundary": 1,
    "Mesh.Optimize": 1,
    "Mesh.OptimizeNetgen": 1,
}
_LOCK = threading.RLock()  # re-entrant: a nested session uses a temporary model
_COUNTER = itertools.count()


def _import_gmsh() -> ModuleType:
    try:
        import gmsh
    except ImportError as exc:  # pragma: no cover - depends on the installation
        raise MeshError(
            "meshing spheres, cylinders and surface files needs the gmsh Python package (pip install gmsh)"
        ) from exc
    return gmsh


@contextmanager
def gmsh_session(mesh_size: float) -> Iterator[ModuleType]:
    """Run gmsh quietly and reproducibly on a fresh model; yield the ``gmsh`` module.

    If gmsh is not initialised it is initialised here (``-nopopup``, no user configuration files,
    Python's Ctrl-C handling left alone) and finalised on exit. If the caller already runs a gmsh
    session, a temporary model is used instead and every option changed here is restored.

    Parameters
    ----------
    mesh_size:
        Target element edge length [m]; sets ``Mesh.MeshSizeMax`` to it and ``Mesh.MeshSizeMin``
        to half of it.

    Raises
    ------
    MeshError
        gmsh is not installed, or any gmsh call inside the block fails (the gmsh message is kept
        and the original exception chained).
    """
    gmsh = _import_gmsh()
    options = dict(_OPTIONS)
    options["Mesh.MeshSizeMax"] = mesh_size
    options["Mesh.MeshSizeMin"] = 0.5 * mesh_size
    with _LOCK:
        owner = not gmsh.isInitialized()
        if owner:
            gmsh.initialize(["softgrasp", "-nopopup"], readConfigFiles=False, interruptible=False)
            _keep_signal_handlers()
            saved: dict[str, float] = {}
            previous_model = ""
        else:
            saved = {key: gmsh.option.getNumber(key) for key in options}
            previous_model = gmsh.model.getCurrent()
        model = f"softgrasp-{next(_COUNTER)}"
        try:
            for key, value in options.items():
                gmsh.option.setNumber(key, value)
            gmsh.model.add(model)
            yield gmsh
        except MeshError:
            raise
        except Exception as exc:
            raise MeshError(f"gmsh failed: {exc}") from exc
        finally:
            _close(gmsh, owner, model, previous_model, saved)


def _keep_signal_handlers() -> None:
    """Give the interpreter's SIGINT and SIGTERM handlers back: gmsh's library installs its own
    at start-up, which end the process at once instead of letting the run clean up."""
    if threading.current_thread() is not threading.main_thread():
        return  # handlers are set from the main thread only
    for sig in (signal.SIGINT, signal.SIGTERM):
        handler = signal.getsignal(sig)
        if handler is not None:
            signal.signal(sig, handler)


def _close(gmsh: ModuleType, owner: bool, model: str, previous: str, saved: dict[str, float]) -> None:
    """End a session: finalise gmsh if we started it, else drop our model and restore options."""
    if owner:
        gmsh.finalize()
        return
    gmsh.model.setCurrent(model)
    gmsh.model.remove()
    for key, value in saved.items():
        gmsh.option.setNumber(key, value)
    if previous:
        gmsh.model.setCurrent(previous)


def compact_nodes(
    points: NDArray[np.float64], cells: NDArray[np.int64]
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Drop nodes no cell refers to and renumber the rest compactly, keeping their order.

    Parameters
    ----------
    points:
        Node coordinates [m], shape ``(N, 3)``.
    cells:
        Node indices into ``points``, shape ``(M, k)``, all in ``0..N-1``.

    Returns
    -------
    tuple
        ``points[used]`` with shape ``(N', 3)`` and the renumbered cells, shape ``(M, k)``.
    """
    used = np.unique(cells)
    new_index = np.full(points.shape[0], -1, dtype=np.int64)
    new_index[used] = np.arange(used.size, dtype=np.int64)
    return points[used], new_index[cells]


def tet_mesh_from_model(gmsh: ModuleType, name: str) -> TetMesh:
    """The linear tetrahedra (gmsh element type 4) of the current gmsh model as a :class:`TetMesh`.

    Nodes not used by any tet (geometric points, nodes of curves and surfaces only) are dropped,
    tets are oriented positively, and the mesh is numbered for memory locality
    (:meth:`TetMesh.reordered`: gmsh's own numbering scatters neighbours across the arrays).

    Raises
    ------
    MeshError
        The model has no tetrahedra, or the result fails :class:`TetMesh` validation.
    """
    tags, coords, _ = gmsh.model.mesh.getNodes()
    _, tet_tags = gmsh.model.mesh.getElementsByType(4)
    if len(tet_tags) == 0:
        raise MeshError("gmsh produced no tetrahedra")
    tags = np.asarray(tags, dtype=np.int64)
    order = np.argsort(tags)
    points = np.asarray(coords, dtype=np.float64).reshape(-1, 3)[order]
    tets = np.searchsorted(tags[order], np.asarray(tet_tags, dtype=np.int64)).reshape(-1, 4)
    points, tets = compact_nodes(points, tets)
    return TetMesh(points, tets, reorient=True, name=name).reordered()


def millimetre_hint(h: float, largest: float) -> str:
    """The clause pointing out that a refused mesh size ``h`` [m] reads as millimetres, where that
    reading (``h`` / 1000) would be accepted (at most ``largest`` [m]); empty otherwise."""
    if h >= 1.0 and h * 1e-3 <= largest:
        return f"the size is in metres (for {h:g} mm write {h * 1e-3:g}); "
    return ""


def check_mesh_size(mesh_size: float, volume: float, what: str, extent: float | None = None) -> float:
    """Validate a mesh size [m] against the tet budget for a solid of ``volume`` [m^3] and, given
    the solid's smallest ``extent`` [m] (its thinnest dimension), against the coarsest mesh that
    still represents it: at least two elements across that extent.

    Returns
    -------
    float
        ``mesh_size`` as a float.

    Raises
    ------
    MeshError
        ``mesh_size`` is not a positive finite number, about more than :data:`MAX_TETS`
        tetrahedra would be needed, or it exceeds half of ``extent`` (fewer than two elements
        across the object, forces that mean nothing: most often a size meant in millimetres given
        as metres). A default size is the caller's to cap at a quarter of ``extent``.
    """
    try:
        h = float(mesh_size)
    except (TypeError, ValueError) as exc:
        raise MeshError(f"{what} mesh_size must be a number in metres, got {mesh_size!r}") from exc
    if not (np.isfinite(h) and h > 0):
        raise MeshError(f"{what} mesh_size must be positive and finite, got {mesh_size!r}")
    if extent is not None and h > 0.5 * extent:
        raise MeshError(
            f"{what} mesh_size {h:.4g} m is coarser than half the object's thinnest dimension "
            f"({extent * 1e3:.3g} mm): fewer than two elements across it, forces that mean nothing; "
            + millimetre_hint(h, 0.5 * extent)
            + f"use mesh_size <= {0.5 * extent:.3g} m"
        )
    expected = TETS_PER_H3 * volume / h**3
    if expected > MAX_TETS:
        h_min = (TETS_PER_H3 * volume / MAX_TETS) ** (1.0 / 3.0)
        raise MeshError(
            f"{what} mesh_size {h:.3g} m is too small: about {expected:.2g} tetrahedra would be "
            f"needed (limit {MAX_TETS:.0e}); use mesh_size >= {h_min:.3g} m"
        )
    return h


def default_mesh_size(box_volume: float) -> float:
    """Default mesh size [m] for an object whose bounding box has ``box_volume`` [m^3].

    One eighth of the geometric mean of the box sides, ``box_volume^(1/3) / 8``: 8 elements along
    each side of a cube, radius/4 for a sphere (a few hundred nodes).
    """
    return float(np.cbrt(box_volume) / 8.0)
