"""Interactive page of a plan run: ``softgrasp view RUN_DIR``.

:func:`write_view` reads the ``frames.npz`` that ``softgrasp plan --out DIR`` writes and turns it into
one self-contained HTML file: the deformed boundary surface of the object, the fingertips and their
forces on the object, for the start of the closing, each closing increment and the final held state,
chosen with a slider and turned with the mouse.

The page needs no network and no plug-in: the data are embedded as JSON and a small inline script
(``static/view.js``, inlined into the page template ``static/view.html``) draws them with the
Canvas 2D API (painter's algorithm: triangles sorted by depth, flat Lambert shading), which works
everywhere, also without a GPU. Node coordinates are stored as whole
micrometres, the first frame absolute and every later one as differences to the previous frame,
which keeps the file small.
"""

from __future__ import annotations

import html
import json
import math
import re
import zipfile
import zlib
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from softgrasp.errors import ConfigError
from softgrasp.io.atomic import write_text

__all__ = ["write_view"]

#: The arrays ``softgrasp plan`` writes into ``frames.npz`` (see ``softgrasp.api.planning.Plan.save``).
_ARRAYS = (
    "travel",
    "positions",
    "centres",
    "forces",
    "held_positions",
    "held_centres",
    "held_forces",
    "facets",
    "fingertip_radius",
    "finger_names",
)

#: Finger colours, in the order of the planner's figures (matplotlib's tab: red, blue, green, ...).
_FINGER_COLOURS = (
    "#d62728",
    "#1f77b4",
    "#2ca02c",
    "#9467bd",
    "#ff7f0e",
    "#8c564b",
    "#e377c2",
    "#bcbd22",
    "#17becf",
)

#: Fingertip centres this close [m] to those of a closing frame mark the travel of the held state.
_SAME_CENTRE_M = 1e-7

#: Default elevation of the camera above the horizontal [deg]: slightly from above.
_ELEVATION_DEG = 24.0


@dataclass(frozen=True)
class _Run:
    """The content of a run's ``frames.npz``, checked (SI units)."""

    travel: NDArray[np.float64]  # (K,)
    positions: NDArray[np.float64]  # (K, N, 3)
    centres: NDArray[np.float64]  # (K, F, 3)
    forces: NDArray[np.float64]  # (K, F, 3)
    held_positions: NDArray[np.float64]  # (N, 3)
    held_centres: NDArray[np.float64]  # (F, 3)
    held_forces: NDArray[np.float64]  # (F, 3)
    facets: NDArray[np.int64]  # (M, 3)
    radius: float
    names: list[str]


def _load_run(run_dir: Path) -> _Run:
    """Read and check ``run_dir/frames.npz``; :class:`ConfigError` saying what to do otherwise."""
    if not run_dir.exists():
        raise ConfigError(
            f"run directory {run_dir} does not exist: run `softgrasp plan --out {run_dir}` first"
        )
    if not run_dir.is_dir():
        raise ConfigError(
            f"{run_dir} is not a directory: give the directory written by `softgrasp plan --out DIR`"
        )
    path = run_dir / "frames.npz"
    if not path.is_file():
        raise ConfigError(
            f"{run_dir} is not a plan run (no frames.npz): run `softgrasp plan --out DIR` first"
        )
    redo = f"rerun `softgrasp plan --out {run_dir}`"
    try:
        with np.load(path, allow_pickle=False) as z:
            missing = [k for k in _ARRAYS if k not in z.files]
            if missing:
                raise ConfigError(f"{path} lacks the arrays {', '.join(missing)}: {redo}")
            raw = {k: np.asarray(z[k]) for k in _ARRAYS}
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile, zlib.error) as exc:
        raise ConfigError(f"{path} is corrupt or not a frames file ({exc}): {redo}") from None

    def bad(what: str) -> ConfigError:
        return ConfigError(f"{path} is corrupt: {what}: {redo}")

    def real(key: str, ndim: int) -> NDArray[np.float64]:
        a = raw[key]
        if a.ndim != ndim or a.dtype.kind not in "iuf":
            raise bad(f"{key} must be a numeric array with {ndim} dimensions, got {a.dtype} {a.shape}")
        a = a.astype(np.float64)
        if not np.all(np.isfinite(a)):
            raise bad(f"{key} holds NaN or infinite values")
        return a

    travel = real("travel", 1)
    positions = real("positions", 3)
    centres = real("centres", 3)
    forces = real("forces", 3)
    held_positions = real("held_positions", 2)
    held_centres = real("held_centres", 2)
    held_forces = real("held_forces", 2)
    radius = real("fingertip_radius", 0)
    facets = raw["facets"]
    names = raw["finger_names"]
    K = travel.shape[0]
    N = positions.shape[1]
    F = held_centres.shape[0]
    if K < 1:
        raise bad("there are no frames")
    if positions.shape != (K, N, 3) or N < 3:
        raise bad(f"positions has shape {positions.shape}, expected ({K}, N, 3)")
    if held_positions.shape != (N, 3):
        raise bad(f"held_positions has shape {held_positions.shape}, expected ({N}, 3)")
    for key, a in (("centres", centres), ("forces", forces)):
        if a.shape != (K, F, 3):
            raise bad(f"{key} has shape {a.shape}, expected ({K}, {F}, 3)")
    if held_centres.shape != (F, 3) or held_forces.shape != (F, 3) or F < 1:
        raise bad(f"held_centres / held_forces have shapes {held_centres.shape} / {held_forces.shape}")
    if names.shape != (F,) or names.dtype.kind != "U":
        raise bad(f"finger_names must be {F} strings, got {names.dtype} {names.shape}")
    if facets.ndim != 2 or facets.shape[1] != 3 or facets.shape[0] < 1 or facets.dtype.kind not in "iu":
        raise bad(f"facets must be an (M, 3) integer array, got {facets.dtype} {facets.shape}")
    facets = facets.astype(np.int64)
    if facets.min() < 0 or facets.max() >= N:
        raise bad(f"facets index nodes outside 0..{N - 1}")
    if not float(radius) > 0.0:
        raise bad(f"fingertip_radius must be > 0, got {float(radius)}")
    return _Run(
        travel=travel,
        positions=positions,
        centres=centres,
        forces=forces,
        held_positions=held_positions,
        held_centres=held_centres,
        held_forces=held_forces,
        facets=facets,
        radius=float(radius),
        names=[str(s) for s in names],
    )


def _orient(points: NDArray[np.float64], tri: NDArray[np.int64]) -> tuple[NDArray[np.int64], bool]:
    """``tri`` with outward normals and whether back faces may be culled.

    Culling is safe only on a consistently oriented closed surface: every directed edge occurs once
    and its reverse occurs too. Such a surface is flipped if it encloses a negative volume.
    """
    n = int(points.shape[0])
    edges = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    key = edges[:, 0] * n + edges[:, 1]
    rev = edges[:, 1] * n + edges[:, 0]
    if np.unique(key).size != key.size or not np.all(np.isin(rev, key)):
        return tri, False
    a, b, c = points[tri[:, 0]], points[tri[:, 1]], points[tri[:, 2]]
    volume = float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum()) / 6.0
    return (tri if volume >= 0.0 else tri[:, ::-1].copy()), True


def _held_travel(run: _Run) -> float | None:
    """Travel [m] of the closing frame whose fingertips sit where the held state's do, if any."""
    gap = np.abs(run.centres - run.held_centres[None]).max(axis=(1, 2))
    k = int(np.argmin(gap))
    return float(run.travel[k]) if gap[k] <= _SAME_CENTRE_M else None


def _default_view(
    points: NDArray[np.float64], centres: NDArray[np.float64], radius: float
) -> tuple[float, float]:
    """Camera azimuth and elevation [deg] that show the fingertips best, slightly from above.

    Every azimuth in 5 degree steps is scored by how much of each fingertip can be seen (all of it
    in front of the object, the part outside the object's outline behind it) plus how far apart
    the fingertips appear.
    """
    centre = 0.5 * (points.min(axis=0) + points.max(axis=0))
    pts = points[:: max(1, points.shape[0] // 4000)] - centre
    size = float(np.linalg.norm(pts, axis=1).max()) or 1.0
    rel = centres - centre
    el = math.radians(_ELEVATION_DEG)
    best_score, best_az = -math.inf, 0.0
    for az_deg in range(0, 360, 5):
        az = math.radians(az_deg)
        e = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        r = np.array([-math.sin(az), math.cos(az), 0.0])
        u = np.cross(e, r)
        to_view = np.column_stack([r, u])
        xy = rel @ to_view
        rho = np.maximum(np.linalg.norm(xy, axis=1), 1e-12)
        # The object's outline in the screen direction of each fingertip.
        outline = ((pts @ to_view) @ (xy / rho[:, None]).T).max(axis=0)
        outside = np.clip((rho + radius - outline) / (2.0 * radius), 0.0, 1.0)
        seen = np.where(rel @ e >= 0.0, 1.0, outside).sum()
        if len(xy) > 1:
            d = np.linalg.norm(xy[:, None] - xy[None], axis=2)
            sep = float(d[np.triu_indices(len(xy), 1)].min()) / size
        else:
            sep = 0.0
        score = float(seen) + 0.5 * min(sep, 1.0)
        if score > best_score + 1e-9:
            best_score, best_az = score, float(az_deg)
    return best_az, _ELEVATION_DEG


def _title(run_dir: Path) -> str:
    """``object (material)`` from the run's plan.json when readable, else the directory name."""
    try:
        doc = json.loads((run_dir / "plan.json").read_text(encoding="utf-8"))
        obj = doc["object"]
        return f"{obj['name']} ({obj['material']['name']}), {run_dir.name}"
    except (OSError, ValueError, KeyError, TypeError):
        return run_dir.name or str(run_dir)


def _page_data(run: _Run, title: str) -> dict:
    """The JSON the page script reads (see the format notes at the top of ``static/view.js``)."""
    used = np.unique(run.facets)
    index = np.full(run.positions.shape[1], -1, dtype=np.int64)
    index[used] = np.arange(used.size)
    tri, cull = _orient(run.positions[0][used], index[run.facets])
    pos_um = np.rint(np.concatenate([run.positions[:, used], run.held_positions[None, used]]) * 1e6).astype(
        np.int64
    )
    steps = np.concatenate([pos_um[:1], np.diff(pos_um, axis=0)])
    held_travel = _held_travel(run)
    frames = []
    K = run.travel.shape[0]
    for k in range(K + 1):
        held = k == K
        travel = held_travel if held else float(run.travel[k])
        c = run.held_centres if held else run.centres[k]
        f = run.held_forces if held else run.forces[k]
        frames.append(
            {
                "label": "held" if held else str(k),
                "held": held,
                "travel_mm": None if travel is None else round(travel * 1e3, 6),
                "centres": np.round(c, 6).tolist(),
                "forces": np.round(f, 6).tolist(),
                "pos": steps[k].ravel().tolist(),
            }
        )
    az, el = _default_view(run.positions[0][used], run.centres[-1], run.radius)
    return {
        "format": "softgrasp.view/1",
        "title": title,
        "nodes": int(used.size),
        "tris": tri.ravel().tolist(),
        "cull": cull,
        "radius": run.radius,
        "fingers": run.names,
        "colours": [_FINGER_COLOURS[i % len(_FINGER_COLOURS)] for i in range(len(run.names))],
        "view": {"azimuth_deg": az, "elevation_deg": el},
        "frames": frames,
    }


def _static(name: str) -> str:
    """The text of ``static/name``, shipped with the package: the page template (``view.html``,
    with ``__TITLE__``, ``__SCRIPT__`` and ``__DATA__`` to fill in) and its script (``view.js``)."""
    return resources.files("softgrasp.viz").joinpath("static", name).read_text(encoding="utf-8")


def _embed(data: dict) -> str:
    """``data`` as JSON safe inside a ``<script>`` element (no ``<``, ``>`` or ``&``)."""
    text = json.dumps(data, separators=(",", ":"), allow_nan=False)
    return text.replace("<", "\\u003c").replace(">", "\\u003e").replace("&", "\\u0026")


def write_view(run_dir: str | Path, out: str | Path | None = None) -> Path:
    """Write the interactive page of the plan run in ``run_dir`` and return its path.

    Parameters
    ----------
    run_dir:
        A directory written by ``softgrasp plan --out DIR`` (it must hold ``frames.npz``).
    out:
        The HTML file to write; default ``run_dir/view.html``.

    The page is self-contained (no network access): the object's boundary surface at the start of
    the closing, after each closing increment and in the held state (the last frame, "held"), the
    fingertips as spheres and the force of each on the object as an arrow labelled in newtons. A
    slider (``input#frame``) picks the frame, ``#readout`` shows its travel [mm] and the finger
    forces [N]; dragging turns the view, the wheel zooms, a double click resets it. The
    displacements from the start can be shown exaggerated (x2 to x20) and the surface coloured by
    its deformation (on by default).

    For scripts the page defines ``window.softgraspView`` (``frames``: number of frames including
    the held one, ``held``: index of the held frame, ``frame``: current index, ``setFrame(i)``) and
    sets ``document.body.dataset.ready`` to ``"1"`` after its first drawing.

    Raises
    ------
    ConfigError
        ``run_dir`` does not exist, is not a plan run or its ``frames.npz`` is corrupt.
    """
    run_dir = Path(run_dir)
    run = _load_run(run_dir)
    title = _title(run_dir)
    parts = {
        "TITLE": html.escape(f"softgrasp view: {title}"),
        "SCRIPT": _static("view.js"),
        "DATA": _embed(_page_data(run, title)),
    }
    page = re.sub(r"__(TITLE|SCRIPT|DATA)__", lambda m: parts[m.group(1)], _static("view.html"))
    return write_text(run_dir / "view.html" if out is None else Path(out), page)
