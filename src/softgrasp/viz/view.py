"""Interactive page of a plan run: ``softgrasp view RUN_DIR``.

:func:`write_view` reads the ``frames.npz`` that ``softgrasp plan --out DIR`` writes and turns it into
one self-contained HTML file: the deformed boundary surface of the object coloured by its
displacement, the fingertips, their forces on the object and the hand's links, for the start of the
closing, each closing increment and the final held state, chosen with a slider and turned with the
mouse.

The page needs no network and no plug-in: the data are embedded as JSON, and three.js (WebGL; the
pinned build ``static/three.min.js`` with its OrbitControls, made by ``tools/vendor_three.sh``) and
the page's script ``static/view.js`` are inlined into the page template ``static/view.html``. Node
coordinates are stored as whole micrometres, the first frame absolute and every later one as
differences to the previous frame, which keeps the file small.
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
    "normal_forces",
    "held_normal_forces",
    "hand_points",
    "held_hand_points",
    "hand_lines",
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

#: Each node's deformation is sent as a whole number of 1 / _LEVELS of the largest.
_LEVELS = 1000

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
    normals: NDArray[np.float64]  # (K, F) normal components of the forces [N]
    held_normals: NDArray[np.float64]  # (F,)
    hand: NDArray[np.float64]  # (K, P, 3) points of the hand's link polylines
    held_hand: NDArray[np.float64]  # (P, 3)
    hand_lines: NDArray[np.int64]  # (L + 1,) where each polyline starts in the points, then P
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
    normals = real("normal_forces", 2)
    held_normals = real("held_normal_forces", 1)
    hand = real("hand_points", 3)
    held_hand = real("held_hand_points", 2)
    hand_lines = raw["hand_lines"]
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
    if normals.shape != (K, F) or held_normals.shape != (F,):
        raise bad(f"normal_forces / held_normal_forces have shapes {normals.shape} / {held_normals.shape}")
    P = held_hand.shape[0]
    if held_hand.shape != (P, 3) or hand.shape != (K, P, 3):
        raise bad(f"hand_points / held_hand_points have shapes {hand.shape} / {held_hand.shape}")
    if (
        hand_lines.ndim != 1
        or hand_lines.dtype.kind not in "iu"
        or hand_lines.size < 1
        or hand_lines[0] != 0
        or hand_lines[-1] != P
        or np.any(np.diff(hand_lines) < (2 if P else 0))
    ):
        raise bad(f"hand_lines must rise from 0 to {P} in steps of at least 2, got {hand_lines.tolist()}")
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
        normals=normals,
        held_normals=held_normals,
        hand=hand,
        held_hand=held_hand,
        hand_lines=hand_lines.astype(np.int64),
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


def _deformation(start: NDArray[np.float64], frames: NDArray[np.float64]) -> NDArray[np.float64]:
    """How far each node moved [m], ``(K, N)``, from ``start`` ``(N, 3)`` to each of ``frames``
    ``(K, N, 3)`` less the rigid motion that best maps ``start`` onto the frame (least squares)."""
    c0 = start.mean(axis=0)
    c = frames.mean(axis=1, keepdims=True)
    H = np.einsum("ni,knj->kij", start - c0, frames - c)
    U, _, Vt = np.linalg.svd(H)
    V, Ut = np.swapaxes(Vt, 1, 2), np.swapaxes(U, 1, 2)
    d = np.sign(np.linalg.det(V @ Ut))
    V[:, :, 2] *= np.where(d == 0.0, 1.0, d)[:, None]  # a rotation, never a reflection
    R = V @ Ut
    fitted = np.einsum("kij,nj->kni", R, start - c0) + c
    return np.linalg.norm(frames - fitted, axis=2)


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


def _plan_doc(run_dir: Path) -> dict | None:
    """The run's ``plan.json`` as read, None when it is missing or unreadable."""
    try:
        doc = json.loads((run_dir / "plan.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return doc if isinstance(doc, dict) else None


def _title(run_dir: Path, doc: dict | None) -> str:
    """``object (material)`` from the run's plan.json ``doc`` when it has them, else the
    directory name."""
    try:
        obj = doc["object"]  # type: ignore[index]
        return f"{obj['name']} ({obj['material']['name']}), {run_dir.name}"
    except (KeyError, TypeError):
        return run_dir.name or str(run_dir)


def _setpoints(doc: dict | None, names: list[str]) -> list[float] | None:
    """Each finger's set-point [N] (``setpoints_N`` of the run's plan.json ``doc``: the normal
    force the force controller closes to), in the order of ``names``; None unless the plan gives
    a finite, positive one for every finger."""
    try:
        given = doc["setpoints_N"]  # type: ignore[index]
        values = [float(given[n]) for n in names]
    except (KeyError, TypeError, ValueError):
        return None
    return values if all(math.isfinite(v) and v > 0 for v in values) else None


def _page_data(run: _Run, title: str, setpoints: list[float] | None = None) -> dict:
    """The JSON the page script reads (see the format notes at the top of ``static/view.js``)."""
    used = np.unique(run.facets)
    index = np.full(run.positions.shape[1], -1, dtype=np.int64)
    index[used] = np.arange(used.size)
    tri, closed = _orient(run.positions[0][used], index[run.facets])
    pos_um = np.rint(np.concatenate([run.positions[:, used], run.held_positions[None, used]]) * 1e6).astype(
        np.int64
    )
    steps = np.concatenate([pos_um[:1], np.diff(pos_um, axis=0)])
    moved = _deformation(
        run.positions[0][used], np.concatenate([run.positions, run.held_positions[None]])[:, used]
    )
    moved_max = float(moved.max())
    levels = np.rint(moved / (moved_max or 1.0) * _LEVELS).astype(np.int64)
    held_travel = _held_travel(run)
    frames = []
    K = run.travel.shape[0]
    for k in range(K + 1):
        held = k == K
        travel = held_travel if held else float(run.travel[k])
        c = run.held_centres if held else run.centres[k]
        f = run.held_forces if held else run.forces[k]
        n = run.held_normals if held else run.normals[k]
        h = run.held_hand if held else run.hand[k]
        frames.append(
            {
                "label": "held" if held else str(k),
                "held": held,
                "travel_mm": None if travel is None else round(travel * 1e3, 6),
                "centres": np.round(c, 6).tolist(),
                "forces": np.round(f, 6).tolist(),
                "normals": np.round(n, 6).tolist(),
                "hand": np.round(h, 6).ravel().tolist(),
                "pos": steps[k].ravel().tolist(),
                "deformation": levels[k].tolist(),
            }
        )
    az, el = _default_view(run.positions[0][used], run.centres[-1], run.radius)
    return {
        "format": "softgrasp.view/2",
        "title": title,
        "nodes": int(used.size),
        "tris": tri.ravel().tolist(),
        "closed": closed,
        "radius": run.radius,
        "fingers": run.names,
        "setpoints": None if setpoints is None else [round(v, 6) for v in setpoints],
        "colours": [_FINGER_COLOURS[i % len(_FINGER_COLOURS)] for i in range(len(run.names))],
        "view": {"azimuth_deg": az, "elevation_deg": el},
        "hand_lines": run.hand_lines.tolist(),
        "deformation_max_m": moved_max,
        "frames": frames,
    }


def _static(name: str) -> str:
    """The text of ``static/name``, shipped with the package: the page template (``view.html``,
    with ``__TITLE__``, ``__THREE__``, ``__SCRIPT__`` and ``__DATA__`` to fill in), three.js
    (``three.min.js``) and the page's script (``view.js``)."""
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

    The page is self-contained (no network access; WebGL through the inlined three.js): the
    object's boundary surface at the start of the closing, after each closing increment and in the
    held state (the last frame, "held", which the page opens on), coloured by each node's
    displacement from the start less the rigid shift (with a colour bar); the fingertips as
    spheres; the force of each on the object as an arrow (lengths proportional to the force, on one
    scale for all frames) labelled with its normal force and the finger's set-point (the plan's
    ``setpoints_N``, when ``run_dir`` holds its plan.json) in newtons; the hand's links as capsules;
    the table during the closing. A slider (``input#frame``) picks the frame, ``#readout`` shows
    its travel [mm] and the finger forces [N]; dragging turns the view, the wheel zooms, a double
    click resets it. The camera frames every frame's scene whichever way it is turned.

    For scripts the page defines ``window.softgraspView`` (``frames``: number of frames including
    the held one, ``held``: index of the held frame, ``frame``: current index, ``setFrame(i)``,
    ``handLinks``: number of link capsules drawn, ``showHand(on)``, ``resetView()``) and sets
    ``document.body.dataset.ready`` to ``"1"`` after its first drawing (``"error"`` without WebGL).

    Raises
    ------
    ConfigError
        ``run_dir`` does not exist, is not a plan run or its ``frames.npz`` is corrupt.
    """
    run_dir = Path(run_dir)
    run = _load_run(run_dir)
    doc = _plan_doc(run_dir)
    title = _title(run_dir, doc)
    parts = {
        "TITLE": html.escape(f"softgrasp view: {title}"),
        "THREE": _static("three.min.js"),
        "SCRIPT": _static("view.js"),
        "DATA": _embed(_page_data(run, title, _setpoints(doc, run.names))),
    }
    page = re.sub(r"__(TITLE|THREE|SCRIPT|DATA)__", lambda m: parts[m.group(1)], _static("view.html"))
    return write_text(run_dir / "view.html" if out is None else Path(out), page)
