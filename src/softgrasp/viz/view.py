"""Interactive page of a plan run: ``softgrasp view RUN_DIR``.

:func:`write_view` reads the ``frames.npz`` that ``softgrasp plan --out DIR`` writes and turns it into
one self-contained HTML file: the deformed boundary surface of the object, the fingertips and their
forces on the object, for the start of the closing, each closing increment and the final held state,
chosen with a slider and turned with the mouse.

The page needs no network and no plug-in: the data are embedded as JSON and a small inline script
draws them with the Canvas 2D API (painter's algorithm: triangles sorted by depth, flat Lambert
shading), which works everywhere, also without a GPU. Node coordinates are stored as whole
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
    """The JSON the page script reads (see the format notes in ``_SCRIPT``)."""
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
        "SCRIPT": _SCRIPT,
        "DATA": _embed(_page_data(run, title)),
    }
    page = re.sub(r"__(TITLE|SCRIPT|DATA)__", lambda m: parts[m.group(1)], _PAGE)
    return write_text(run_dir / "view.html" if out is None else Path(out), page)


_PAGE = """<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<meta name="generator" content="softgrasp view">
<title>__TITLE__</title>
<style>
html, body { margin: 0; height: 100%; }
body {
  display: flex; flex-direction: column; color: #1f2328; background: #f3f4f6;
  font: 14px/1.4 system-ui, -apple-system, "Segoe UI", Roboto, "Helvetica Neue", Arial, sans-serif;
}
header {
  display: flex; flex-wrap: wrap; align-items: center; gap: 6px 22px; padding: 8px 14px;
  background: #fff; border-bottom: 1px solid #d0d7de;
}
header h1 { margin: 0; font-size: 15px; font-weight: 600; }
header label { white-space: nowrap; }
.controls { display: flex; align-items: center; gap: 8px; }
#frame { width: 240px; }
#frame-label { min-width: 5.5em; font-variant-numeric: tabular-nums; }
#play { width: 2.2em; }
#readout { flex-basis: 100%; font-variant-numeric: tabular-nums; }
#readout .finger { white-space: nowrap; }
.dot { display: inline-block; width: 10px; height: 10px; border-radius: 50%; margin: 0 4px 0 2px; }
main { position: relative; flex: 1; min-height: 200px; }
#view { position: absolute; inset: 0; width: 100%; height: 100%; cursor: grab; touch-action: none; }
#view.dragging { cursor: grabbing; }
#legend {
  position: absolute; right: 10px; top: 10px; padding: 5px 10px; font-size: 12px; line-height: 1.7;
  background: rgba(255, 255, 255, 0.88); border: 1px solid #d0d7de; border-radius: 6px;
  pointer-events: none;
}
.swatch { display: inline-block; width: 18px; height: 10px; margin-right: 6px; vertical-align: -1px; }
.ramp { display: inline-block; width: 90px; height: 10px; margin: 0 5px; vertical-align: -1px; }
#help { position: absolute; right: 12px; bottom: 8px; font-size: 12px; color: #6e7781; pointer-events: none; }
</style>
</head>
<body>
<header>
  <h1 id="title"></h1>
  <div class="controls">
    <button id="play" type="button" title="play the closing">&#9654;</button>
    <label for="frame">frame</label>
    <input type="range" id="frame" min="0" max="0" step="1" value="0">
    <output id="frame-label" for="frame"></output>
  </div>
  <div class="controls">
    <label>deformation shown
      <select id="scale" title="exaggerate the displacements from the start">
        <option value="1" selected>&times;1 (true)</option><option value="2">&times;2</option>
        <option value="5">&times;5</option><option value="10">&times;10</option>
        <option value="20">&times;20</option>
      </select>
    </label>
    <label><input type="checkbox" id="colour" checked> colour by deformation</label>
  </div>
  <div id="readout" aria-live="polite"></div>
</header>
<main>
  <canvas id="view"></canvas>
  <div id="legend"></div>
  <div id="help">drag: rotate &middot; wheel: zoom &middot; double-click: reset view</div>
</main>
<script type="application/json" id="softgrasp-data">__DATA__</script>
<script>
__SCRIPT__
</script>
</body>
</html>
"""

# The page script. Data format (softgrasp.view/1): `nodes` boundary nodes, `tris` flat node triples
# (outward when `cull`), `frames[k]` with `pos` (node coordinates in whole micrometres, frame 0
# absolute and every later frame the difference to the previous one), `centres` [m], `forces` [N],
# `travel_mm` and `held`; `radius` of the fingertips [m], `fingers` names, `colours`, default `view`.
_SCRIPT = r"""
"use strict";
(function () {
  const D = JSON.parse(document.getElementById("softgrasp-data").textContent);
  const $ = id => document.getElementById(id);
  const canvas = $("view"), ctx = canvas.getContext("2d"), slider = $("frame");

  const BACKGROUND = "#f3f4f6";
  const OBJECT_RGB = [222, 186, 138];
  // Colour by deformation: from the object's colour (none) through orange to plum (the largest).
  const RAMP = [[0, OBJECT_RGB], [0.5, [240, 128, 48]], [1, [128, 34, 104]]];
  const LIGHT = normalise([-0.45, 0.6, 0.66]);  // fixed in camera space: upper left, in front
  const SHADES = 96, TINTS = 24;  // quantised brightness and deformation colour
  const KEY_SPAN = 4194304;  // sort key = quantised depth * KEY_SPAN + item index (< 2^22)

  const nNodes = D.nodes, tris = Int32Array.from(D.tris), nTri = tris.length / 3;
  const nF = D.fingers.length, tipR = D.radius, nFrames = D.frames.length;
  const heldIndex = D.frames.findIndex(f => f.held);

  function normalise(v) {
    const l = Math.hypot(v[0], v[1], v[2]) || 1;
    return [v[0] / l, v[1] / l, v[2] / l];
  }
  function rgb(c) { return "rgb(" + c.map(v => Math.max(0, Math.min(255, Math.round(v)))).join(",") + ")"; }
  function mix(a, b, t) { return a.map((v, i) => v + (b[i] - v) * t); }
  function ramp(x) {
    for (let i = 1; i < RAMP.length; i++) {
      const [x0, c0] = RAMP[i - 1], [x1, c1] = RAMP[i];
      if (x <= x1) return mix(c0, c1, (x - x0) / (x1 - x0));
    }
    return RAMP[RAMP.length - 1][1];
  }
  function shadeHex(hex, k) {  // k > 0 towards white, k < 0 towards black
    const n = parseInt(hex.slice(1), 16), c = [(n >> 16) & 255, (n >> 8) & 255, n & 255];
    return rgb(k >= 0 ? mix(c, [255, 255, 255], k) : c.map(v => v * (1 + k)));
  }

  // Frames: node positions [m] decoded from the micrometre differences, and the deformation of
  // each node, |u - mean u| with u its displacement from the start (the mean is the rigid shift).
  const frames = [];
  let dMax = 0;
  {
    const acc = new Float64Array(3 * nNodes);
    for (const f of D.frames) {
      const p = new Float32Array(3 * nNodes);
      for (let i = 0; i < p.length; i++) { acc[i] += f.pos[i]; p[i] = acc[i] * 1e-6; }
      delete f.pos;
      const p0 = frames.length ? frames[0].p : p, mean = [0, 0, 0], def = new Float32Array(nNodes);
      for (let i = 0; i < 3 * nNodes; i++) mean[i % 3] += (p[i] - p0[i]) / nNodes;
      for (let i = 0; i < nNodes; i++) {
        def[i] = Math.hypot(p[3 * i] - p0[3 * i] - mean[0], p[3 * i + 1] - p0[3 * i + 1] - mean[1],
                            p[3 * i + 2] - p0[3 * i + 2] - mean[2]);
        dMax = Math.max(dMax, def[i]);
      }
      frames.push({
        p: p, def: def, centres: f.centres, forces: f.forces, held: f.held, label: f.label,
        travel: f.travel_mm, mag: f.forces.map(v => Math.hypot(v[0], v[1], v[2])),
      });
    }
  }

  // The scene: centre and size of the object at the start, largest force, table grid.
  const scene = (() => {
    const p = frames[0].p, lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
    for (let i = 0; i < 3 * nNodes; i++) {
      lo[i % 3] = Math.min(lo[i % 3], p[i]); hi[i % 3] = Math.max(hi[i % 3], p[i]);
    }
    const c = [0, 1, 2].map(a => 0.5 * (lo[a] + hi[a]));
    let R = 0;
    for (let i = 0; i < nNodes; i++) {
      R = Math.max(R, Math.hypot(p[3 * i] - c[0], p[3 * i + 1] - c[1], p[3 * i + 2] - c[2]));
    }
    R = R || 1e-3;
    let fMax = 0;
    for (const f of frames) for (const m of f.mag) fMax = Math.max(fMax, m);
    const raw = R / 3, pow = Math.pow(10, Math.floor(Math.log10(raw)));
    const grid = [1, 2, 5, 10].map(m => m * pow).find(g => g >= raw);
    return { c: c, R: R, fMax: fMax, arrowMax: 0.55 * R, grid: grid, half: Math.ceil(1.3 * R / grid) * grid };
  })();

  // Camera: orbit around the scene centre, z up; `dist` gives a mild perspective.
  const cam = { az: 0, el: 0, zoom: 1, dist: 7 * scene.R };
  const fit = { x0: -1, x1: 1, y0: -1, y1: 1 };  // the default view's extent in view units
  let W = 300, H = 150, scale = 1, panX = 0, panY = 0, exaggerate = 1, colourOn = true;
  let current = 0, drawCount = 0, lastDrawMs = 0;

  function basis() {
    const ca = Math.cos(cam.az), sa = Math.sin(cam.az), ce = Math.cos(cam.el), se = Math.sin(cam.el);
    return { r: [-sa, ca, 0], u: [-se * ca, -se * sa, ce], e: [ce * ca, ce * sa, se] };
  }

  // View coordinates of a world point (x right, y up, z towards the camera) and its screen point.
  function project(B, P) {
    const dx = P[0] - scene.c[0], dy = P[1] - scene.c[1], dz = P[2] - scene.c[2];
    const vx = dx * B.r[0] + dy * B.r[1];
    const vy = dx * B.u[0] + dy * B.u[1] + dz * B.u[2];
    const vz = dx * B.e[0] + dy * B.e[1] + dz * B.e[2];
    const s = cam.dist / (cam.dist - vz), k = cam.zoom * scale * s;
    return { vx: vx, vy: vy, vz: vz, s: s,
             X: W / 2 + cam.zoom * panX + k * vx, Y: H / 2 - cam.zoom * panY - k * vy };
  }

  // Fingertip centre as drawn: with exaggerated displacements it moves with the surface nearest
  // to it, so that it still touches the object as it does.
  function tipCentre(f, i, g) {
    const c = f.centres[i];
    if (g === 1) return c;
    if (!f.near) {
      f.near = f.centres.map(q => {
        let best = 0, dBest = Infinity;
        for (let j = 0; j < nNodes; j++) {
          const d = (f.p[3 * j] - q[0]) ** 2 + (f.p[3 * j + 1] - q[1]) ** 2 + (f.p[3 * j + 2] - q[2]) ** 2;
          if (d < dBest) { dBest = d; best = j; }
        }
        return best;
      });
    }
    const j = 3 * f.near[i], p0 = frames[0].p;
    return [0, 1, 2].map(a => c[a] + (g - 1) * (f.p[j + a] - p0[j + a]));
  }

  // Force arrow: its tip where the fingertip touches, its length proportional to the force.
  function arrowEnds(f, i, g) {
    const m = f.mag[i];
    if (!(scene.fMax > 0) || !(m > 1e-6 * scene.fMax)) return null;
    const c = tipCentre(f, i, g), F = f.forces[i], L = scene.arrowMax * m / scene.fMax;
    const tip = [0, 1, 2].map(a => c[a] + tipR * F[a] / m);
    return { tip: tip, tail: [0, 1, 2].map(a => tip[a] - L * F[a] / m) };
  }

  // Extent of everything (all frames, fingertips, arrows) seen from the default camera.
  function fitDefault() {
    cam.az = D.view.azimuth_deg * Math.PI / 180;
    cam.el = D.view.elevation_deg * Math.PI / 180;
    cam.zoom = 1;
    const B = basis();
    let x0 = Infinity, x1 = -Infinity, y0 = Infinity, y1 = -Infinity;
    const add = (P, pad) => {
      const q = project(B, P);
      x0 = Math.min(x0, q.vx * q.s - pad); x1 = Math.max(x1, q.vx * q.s + pad);
      y0 = Math.min(y0, q.vy * q.s - pad); y1 = Math.max(y1, q.vy * q.s + pad);
    };
    const stride = Math.max(1, Math.floor(nNodes * nFrames / 60000));
    for (const f of frames) {
      for (let i = 0; i < nNodes; i += stride) add([f.p[3 * i], f.p[3 * i + 1], f.p[3 * i + 2]], 0);
      for (let i = 0; i < nF; i++) {
        add(tipCentre(f, i, 1), tipR);
        const a = arrowEnds(f, i, 1);
        if (a) add(a.tail, 0);
      }
    }
    Object.assign(fit, { x0: x0, x1: x1, y0: y0, y1: y1 });
  }

  function layout() {
    const rect = canvas.getBoundingClientRect(), dpr = window.devicePixelRatio || 1;
    W = Math.max(1, rect.width); H = Math.max(1, rect.height);
    canvas.width = Math.round(W * dpr); canvas.height = Math.round(H * dpr);
    ctx.setTransform(canvas.width / W, 0, 0, canvas.height / H, 0, 0);
    const mx = Math.min(110, 0.15 * W), my = Math.min(30, 0.08 * H);  // room for the arrow labels
    scale = Math.min((W - 2 * mx) / (fit.x1 - fit.x0), (H - 2 * my) / (fit.y1 - fit.y0));
    panX = -scale * 0.5 * (fit.x0 + fit.x1);
    panY = -scale * 0.5 * (fit.y0 + fit.y1);
  }

  // Fill styles by deformation tint and brightness (above 1: a highlight towards white); the
  // outline of a triangle is a little darker than its fill.
  const fillStyles = [], edgeStyles = [];
  for (let t = 0; t < TINTS; t++) {
    const base = ramp(t / (TINTS - 1));
    for (let l = 0; l < SHADES; l++) {
      const b = 1.2 * l / (SHADES - 1);
      const c = b <= 1 ? base.map(v => v * b) : mix(base, [255, 255, 255], (b - 1) / 0.5);
      fillStyles.push(rgb(c));
      edgeStyles.push(rgb(c.map(v => 0.8 * v)));
    }
  }

  // Work arrays, sized once.
  const VX = new Float32Array(nNodes), VY = new Float32Array(nNodes), VZ = new Float32Array(nNodes);
  const SX = new Float32Array(nNodes), SY = new Float32Array(nNodes);
  const keys = new Float64Array(nTri + nF), style = new Uint16Array(nTri);

  function drawTable(B, alpha) {
    const c = scene.c, h = scene.half, g = scene.grid;
    const x0 = Math.round(c[0] / g) * g - h, y0 = Math.round(c[1] / g) * g - h, n = Math.round(2 * h / g);
    const P = (x, y) => project(B, [x, y, 0]);
    ctx.save();
    ctx.globalAlpha = alpha;
    ctx.beginPath();
    [P(x0, y0), P(x0 + 2 * h, y0), P(x0 + 2 * h, y0 + 2 * h), P(x0, y0 + 2 * h)].forEach(
      (q, i) => (i ? ctx.lineTo(q.X, q.Y) : ctx.moveTo(q.X, q.Y)));
    ctx.closePath();
    ctx.fillStyle = "rgba(120, 132, 148, 0.14)";
    ctx.fill();
    ctx.beginPath();
    for (let i = 0; i <= n; i++) {
      const u = x0 + i * g, v = y0 + i * g;
      for (const [a, b] of [[P(u, y0), P(u, y0 + 2 * h)], [P(x0, v), P(x0 + 2 * h, v)]]) {
        ctx.moveTo(a.X, a.Y); ctx.lineTo(b.X, b.Y);
      }
    }
    ctx.strokeStyle = "rgba(96, 108, 124, 0.3)";
    ctx.lineWidth = 1;
    ctx.stroke();
    ctx.restore();
  }

  function drawTip(q, i) {
    const rp = Math.max(1.5, cam.zoom * scale * tipR * q.s), col = D.colours[i];
    const g = ctx.createRadialGradient(q.X - 0.4 * rp, q.Y - 0.45 * rp, 0.05 * rp, q.X, q.Y, rp);
    g.addColorStop(0, shadeHex(col, 0.75));
    g.addColorStop(0.45, col);
    g.addColorStop(1, shadeHex(col, -0.45));
    ctx.beginPath();
    ctx.arc(q.X, q.Y, rp, 0, 2 * Math.PI);
    ctx.fillStyle = g;
    ctx.fill();
    ctx.lineWidth = 1;
    ctx.strokeStyle = shadeHex(col, -0.55);
    ctx.stroke();
  }

  function label(text, x, y, align, colour) {
    ctx.font = "600 13px system-ui, -apple-system, 'Segoe UI', Roboto, Arial, sans-serif";
    ctx.textAlign = align;
    ctx.textBaseline = "middle";
    ctx.lineJoin = "round";
    ctx.lineWidth = 4;
    ctx.strokeStyle = "rgba(255, 255, 255, 0.92)";
    ctx.strokeText(text, x, y);
    ctx.fillStyle = colour;
    ctx.fillText(text, x, y);
  }

  // Force arrows and their labels, over everything; dashed when the fingertip is behind the object.
  function drawArrows(f, B, tips) {
    const o = project(B, scene.c);
    for (let i = 0; i < nF; i++) {
      const q = tips[i], col = D.colours[i], dark = shadeHex(col, -0.25);
      const behind = q.vz < -0.3 * scene.R;
      const a = arrowEnds(f, i, exaggerate);
      let ux = q.X - o.X, uy = q.Y - o.Y, at = null;
      if (a) {
        const t = project(B, a.tip), s = project(B, a.tail), len = Math.hypot(t.X - s.X, t.Y - s.Y);
        if (len > 1) {
          const dx = (t.X - s.X) / len, dy = (t.Y - s.Y) / len, head = Math.min(16, 0.45 * len + 4);
          const bx = t.X - head * dx, by = t.Y - head * dy;
          ctx.save();
          ctx.globalAlpha = behind ? 0.65 : 1;
          ctx.lineCap = "round";
          ctx.setLineDash(behind ? [7, 5] : []);
          for (const [w, st] of [[7, "rgba(255, 255, 255, 0.9)"], [3.2, dark]]) {
            ctx.beginPath(); ctx.moveTo(s.X, s.Y); ctx.lineTo(bx, by);
            ctx.lineWidth = w; ctx.strokeStyle = st; ctx.stroke();
          }
          ctx.setLineDash([]);
          ctx.beginPath();
          ctx.moveTo(t.X, t.Y);
          ctx.lineTo(bx - 0.5 * head * dy, by + 0.5 * head * dx);
          ctx.lineTo(bx + 0.5 * head * dy, by - 0.5 * head * dx);
          ctx.closePath();
          ctx.lineWidth = 2; ctx.strokeStyle = "rgba(255, 255, 255, 0.9)"; ctx.stroke();
          ctx.fillStyle = dark; ctx.fill();
          ctx.restore();
          ux = -dx; uy = -dy; at = s;
        }
      }
      const l = Math.hypot(ux, uy) || 1;
      ux /= l; uy /= l;
      if (!at) {  // no arrow: the label beside the fingertip, away from the object
        const rp = cam.zoom * scale * tipR * q.s;
        at = { X: q.X + rp * ux, Y: q.Y + rp * uy };
      }
      const align = ux > 0.35 ? "left" : ux < -0.35 ? "right" : "center";
      label(D.fingers[i] + ": " + f.mag[i].toFixed(2) + " N", at.X + 8 * ux, at.Y + 10 * uy, align, dark);
    }
  }

  // A small axis cross in the lower right corner (x, y on the table, z up).
  function drawAxes(B) {
    const ox = W - 40, oy = H - 64, L = 22;
    ctx.save();
    ctx.lineWidth = 1.5; ctx.strokeStyle = "#57606a"; ctx.fillStyle = "#57606a";
    ctx.font = "11px system-ui, sans-serif"; ctx.textAlign = "center"; ctx.textBaseline = "middle";
    [["x", [1, 0, 0]], ["y", [0, 1, 0]], ["z", [0, 0, 1]]].forEach(([name, v]) => {
      const x = v[0] * B.r[0] + v[1] * B.r[1], y = v[0] * B.u[0] + v[1] * B.u[1] + v[2] * B.u[2];
      ctx.beginPath(); ctx.moveTo(ox, oy); ctx.lineTo(ox + L * x, oy - L * y); ctx.stroke();
      ctx.fillText(name, ox + (L + 8) * x, oy - (L + 8) * y);
    });
    ctx.restore();
  }

  function draw() {
    const t0 = performance.now();
    const f = frames[current], p = f.p, p0 = frames[0].p, g = exaggerate, B = basis();
    ctx.fillStyle = BACKGROUND;
    ctx.fillRect(0, 0, W, H);
    const table = !f.held;
    if (table && cam.el >= 0) drawTable(B, 1);

    // Project the nodes (displacements from the start exaggerated by g).
    let zMin = Infinity, zMax = -Infinity;
    const k = cam.zoom * scale, cx = W / 2 + cam.zoom * panX, cy = H / 2 - cam.zoom * panY;
    for (let i = 0; i < nNodes; i++) {
      const j = 3 * i;
      const dx = p0[j] + g * (p[j] - p0[j]) - scene.c[0];
      const dy = p0[j + 1] + g * (p[j + 1] - p0[j + 1]) - scene.c[1];
      const dz = p0[j + 2] + g * (p[j + 2] - p0[j + 2]) - scene.c[2];
      const vx = dx * B.r[0] + dy * B.r[1];
      const vy = dx * B.u[0] + dy * B.u[1] + dz * B.u[2];
      const vz = dx * B.e[0] + dy * B.e[1] + dz * B.e[2];
      const s = k * cam.dist / (cam.dist - vz);
      VX[i] = vx; VY[i] = vy; VZ[i] = vz;
      SX[i] = cx + s * vx;
      SY[i] = cy - s * vy;
      if (vz < zMin) zMin = vz;
      if (vz > zMax) zMax = vz;
    }
    const tips = [];
    for (let i = 0; i < nF; i++) {
      const q = project(B, tipCentre(f, i, g));
      tips.push(q);
      zMin = Math.min(zMin, q.vz); zMax = Math.max(zMax, q.vz);
    }
    const zScale = (1 << 30) / Math.max(zMax - zMin, 1e-12);
    const tint = colourOn && dMax > 0 ? (TINTS - 1) / dMax : 0;

    // Visible triangles: their style and depth key (sorted: far ones first).
    let n = 0, edgeSum = 0, edgeCount = 0;
    for (let t = 0; t < nTri; t++) {
      const a = tris[3 * t], b = tris[3 * t + 1], c = tris[3 * t + 2];
      const cross = (SX[b] - SX[a]) * (SY[c] - SY[a]) - (SY[b] - SY[a]) * (SX[c] - SX[a]);
      if (D.cull && cross >= 0) continue;  // a back face (screen y points down)
      const ux = VX[b] - VX[a], uy = VY[b] - VY[a], uz = VZ[b] - VZ[a];
      const wx = VX[c] - VX[a], wy = VY[c] - VY[a], wz = VZ[c] - VZ[a];
      let nx = uy * wz - uz * wy, ny = uz * wx - ux * wz, nz = ux * wy - uy * wx;
      let l = Math.hypot(nx, ny, nz);
      if (!(l > 0)) continue;
      if (!D.cull && nz < 0) l = -l;  // two-sided lighting
      const lambert = Math.max(0, (nx * LIGHT[0] + ny * LIGHT[1] + nz * LIGHT[2]) / l);
      const bright = 0.45 + 0.55 * lambert + 0.12 * Math.pow(lambert, 12);
      const shade = Math.min(SHADES - 1, Math.round(bright / 1.2 * (SHADES - 1)));
      const d = Math.round(tint * (f.def[a] + f.def[b] + f.def[c]) / 3);
      style[t] = Math.min(TINTS - 1, d) * SHADES + shade;
      keys[n++] = Math.floor(((VZ[a] + VZ[b] + VZ[c]) / 3 - zMin) * zScale) * KEY_SPAN + t;
      if ((t & 15) === 0) { edgeSum += Math.abs(SX[b] - SX[a]) + Math.abs(SY[b] - SY[a]); edgeCount++; }
    }
    for (let i = 0; i < nF; i++) keys[n++] = Math.floor((tips[i].vz - zMin) * zScale) * KEY_SPAN + nTri + i;
    const order = keys.subarray(0, n).sort();

    // A light outline on coarse meshes; on fine ones the edges only close the seams.
    const coarse = edgeSum / Math.max(1, edgeCount) > 7, width = coarse ? 0.7 : 0.6;
    const edges = coarse ? edgeStyles : fillStyles;
    ctx.lineJoin = "round";
    ctx.lineWidth = width;
    for (let j = 0; j < n; j++) {
      const t = order[j] % KEY_SPAN;
      if (t >= nTri) { drawTip(tips[t - nTri], t - nTri); ctx.lineWidth = width; continue; }
      const a = tris[3 * t], b = tris[3 * t + 1], c = tris[3 * t + 2], st = style[t];
      ctx.beginPath();
      ctx.moveTo(SX[a], SY[a]); ctx.lineTo(SX[b], SY[b]); ctx.lineTo(SX[c], SY[c]);
      ctx.closePath();
      ctx.fillStyle = fillStyles[st];
      ctx.fill();
      ctx.strokeStyle = edges[st];
      ctx.stroke();
    }
    if (table && cam.el < 0) drawTable(B, 0.6);
    drawArrows(f, B, tips);
    drawAxes(B);
    drawCount++;
    lastDrawMs = performance.now() - t0;
  }

  let pending = false;
  function requestDraw() {
    if (pending) return;
    pending = true;
    requestAnimationFrame(() => { pending = false; draw(); });
  }

  function describe(f, k) {
    $("frame-label").textContent = f.held ? "held" : "step " + k + " / " + (heldIndex - 1);
    const readout = $("readout"), travel = f.travel === null ? "" : "travel " + f.travel.toFixed(3) + " mm";
    readout.textContent = (f.held ? "held by the fingers alone (table removed)" + (travel ? ", " : "") : "") +
      travel + ": ";
    for (let i = 0; i < nF; i++) {
      const span = document.createElement("span"), dot = document.createElement("span");
      span.className = "finger";
      dot.className = "dot";
      dot.style.background = D.colours[i];
      span.append(dot, D.fingers[i] + " " + f.mag[i].toFixed(3) + " N");
      readout.append(span, i + 1 < nF ? ",  " : "");
    }
  }

  function setFrame(i) {
    current = Math.max(0, Math.min(nFrames - 1, Math.round(Number(i)) || 0));
    slider.value = String(current);
    describe(frames[current], current);
    draw();
  }

  // Controls.
  $("title").textContent = D.title;
  slider.max = String(nFrames - 1);
  slider.addEventListener("input", () => setFrame(slider.value));
  $("scale").addEventListener("change", e => { exaggerate = Number(e.target.value) || 1; draw(); });
  $("colour").addEventListener("change", e => { colourOn = e.target.checked; legendRamp(); draw(); });
  let timer = null;
  const play = $("play");
  function stop() { clearInterval(timer); timer = null; play.innerHTML = "&#9654;"; }
  play.addEventListener("click", () => {
    if (timer) { stop(); return; }
    if (current >= nFrames - 1) setFrame(0);
    play.innerHTML = "&#10074;&#10074;";
    timer = setInterval(() => { if (current >= nFrames - 1) stop(); else setFrame(current + 1); }, 700);
  });
  let drag = null;
  canvas.addEventListener("pointerdown", e => {
    drag = { x: e.clientX, y: e.clientY };
    canvas.setPointerCapture(e.pointerId);
    canvas.classList.add("dragging");
  });
  canvas.addEventListener("pointermove", e => {
    if (!drag) return;
    cam.az -= 0.01 * (e.clientX - drag.x);
    cam.el = Math.max(-1.5, Math.min(1.5, cam.el + 0.01 * (e.clientY - drag.y)));
    drag = { x: e.clientX, y: e.clientY };
    requestDraw();
  });
  const release = () => { drag = null; canvas.classList.remove("dragging"); };
  canvas.addEventListener("pointerup", release);
  canvas.addEventListener("pointercancel", release);
  canvas.addEventListener("wheel", e => {
    e.preventDefault();
    cam.zoom = Math.max(0.2, Math.min(20, cam.zoom * Math.exp(-0.0015 * e.deltaY)));
    requestDraw();
  }, { passive: false });
  canvas.addEventListener("dblclick", () => { fitDefault(); layout(); requestDraw(); });
  new ResizeObserver(() => { layout(); requestDraw(); }).observe(canvas);

  // Legend.
  const legend = $("legend");
  const row = html => {
    const d = document.createElement("div");
    d.innerHTML = html;
    legend.append(d);
    return d;
  };
  row('<span class="swatch" style="background:' + rgb(OBJECT_RGB) + '"></span>object');
  const tipsRow = row("");
  D.colours.forEach(c => {
    const dot = document.createElement("span");
    dot.className = "dot"; dot.style.background = c;
    tipsRow.append(dot);
  });
  tipsRow.append(" fingertips");
  row("&#10230; force on the object, &prop; |F| (up to " + scene.fMax.toFixed(2) + " N)");
  const rampRow = row('deformation 0<span class="ramp" style="background:linear-gradient(to right,' +
    RAMP.map(s => rgb(s[1]) + " " + 100 * s[0] + "%").join(",") + ')"></span>' +
    (1e3 * dMax).toFixed(2) + " mm");
  rampRow.title = "displacement from the start, less the mean (rigid) shift";
  function legendRamp() { rampRow.style.display = colourOn && dMax > 0 ? "" : "none"; }
  legendRamp();
  row('<span class="swatch" style="background:rgba(120,132,148,0.3)"></span>table, z = 0');

  window.softgraspView = {
    frames: nFrames,
    held: heldIndex,
    get frame() { return current; },
    setFrame: setFrame,
    redraw: draw,
    get drawCount() { return drawCount; },
    get lastDrawMs() { return lastDrawMs; },
  };

  fitDefault();
  layout();
  setFrame(0);
  document.body.dataset.ready = "1";
})();
"""
