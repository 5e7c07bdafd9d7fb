"""Figures of a planned grasp: force against closing increment and against penetration per
finger, and the 3D picture of the deformed object with the fingertips, forces and hand."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from softgrasp.io.atomic import atomic_write
from softgrasp.viz.figure import as_array, check_names, finger_style, pyplot, save_curve

__all__ = ["plot_grasp_3d", "plot_plan_force_penetration", "plot_plan_forces"]


def plot_plan_forces(
    increments: NDArray[np.float64],
    force_norms: NDArray[np.float64],
    names: Sequence[str],
    path: str | Path,
    *,
    setpoints: Sequence[float] | None = None,
    held_at: int | None = None,
    title: str = "Grasping forces applied by the fingers",
    quantity: str = "force",
) -> Path:
    """A force on each finger against the closing increment (paper Fig. 13 style).

    Parameters
    ----------
    increments: closing increments (step numbers or closing parameter), shape (K,).
    force_norms: the force [N] on each finger at each increment (its norm, or its normal
        component), shape (K, n_f).
    names: one label per finger (``thumb``, ``first``, ``middle`` ...).
    path: PNG file to write.
    setpoints: each finger's set-point [N] (from the held state: the table removed, the fingers
        carrying the weight), drawn one step after the last increment and named in the legend:
        the closing ends on the table, so its last forces are not the set-points.
    held_at: the increment (index) the object was held from, where the dotted line to the
        set-points starts (default the last: increments past it bracketed the least squeeze).
    title: figure title.  quantity: what the forces are, for the y axis's label.

    Raises
    ------
    ValueError: inconsistent shapes, non-finite values or a wrong number of names.
    """
    x = as_array("increments", increments, (None,))
    f = as_array("force_norms", force_norms, (x.shape[0], None))
    names = check_names(names, f.shape[1])
    held = None if setpoints is None else as_array("setpoints", setpoints, (f.shape[1],))
    x_held = float(x[-1] + (x[-1] - x[-2] if len(x) > 1 else 1.0)) if len(x) else 1.0
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4.4), dpi=120)
    for i, name in enumerate(names):
        colour, marker = finger_style(i)
        label = name if held is None else f"{name} (set-point {held[i]:.3g} N)"
        ax.plot(x, f[:, i], marker=marker, ms=4.0, lw=1.6, color=colour, label=label)
        if held is not None:
            if len(x):
                k = len(x) - 1 if held_at is None else int(held_at)
                ax.plot([x[k], x_held], [f[k, i], held[i]], lw=1.0, ls=":", color=colour)
            ax.plot([x_held], [held[i]], marker="*", ms=11.0, color=colour, ls="none")
    if np.all(x == np.round(x)):
        from matplotlib.ticker import MaxNLocator

        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    if held is not None:
        # The held state gets its own tick: it is no closing increment.
        lo, hi = ax.get_xlim()
        ticks = [float(v) for v in ax.get_xticks() if lo <= v <= (x[-1] if len(x) else lo)]
        spacing = float(np.median(np.diff(ticks))) if len(ticks) > 1 else 1.0
        ticks = [v for v in ticks if x_held - v >= 0.5 * spacing]  # no label run into "held"
        ax.set_xticks([*ticks, x_held], [f"{v:g}" for v in ticks] + ["held"])
        ax.set_xlim(lo, hi)
        top = 1.15 * float(max(f.max(initial=0.0), held.max()))
        if top > 0:
            ax.set_ylim(top=top)
    ax.set_xlabel(
        "closing increment" if held is None else "closing increment, then held with the table removed (★)"
    )
    ax.set_ylabel(f"{quantity} [N]")
    ax.set_title(title)
    out = save_curve(plt, fig, ax, path, legend_loc="upper left")
    return out


def plot_plan_force_penetration(
    penetrations: NDArray[np.float64],
    force_norms: NDArray[np.float64],
    names: Sequence[str],
    path: str | Path,
    *,
    title: str = "Force against penetration of each finger",
) -> Path:
    """Force norm against penetration [mm] for each finger of a planned grasp (paper Fig. 15 style).

    Parameters
    ----------
    penetrations: penetration [m] of each fingertip into the object, shape (K, n_f).
    force_norms: contact force norm [N] on each finger, shape (K, n_f).
    names: one label per finger.
    path: PNG file to write.
    title: figure title.

    Raises
    ------
    ValueError: inconsistent shapes, non-finite values or a wrong number of names.
    """
    d = as_array("penetrations", penetrations, (None, None))
    f = as_array("force_norms", force_norms, d.shape)
    names = check_names(names, f.shape[1])
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4.4), dpi=120)
    for i, name in enumerate(names):
        colour, marker = finger_style(i)
        ax.plot(1e3 * d[:, i], f[:, i], marker=marker, ms=4.0, lw=1.6, color=colour, label=name)
    ax.set_xlabel("penetration [mm]")
    ax.set_ylabel("force [N]")
    ax.set_title(title)
    out = save_curve(plt, fig, ax, path, legend_loc="upper left")
    return out


def _arrow3d_class():
    """A FancyArrowPatch drawn between two 3D points (2D arrowheads look better than 3D quiver)."""
    from matplotlib.patches import FancyArrowPatch
    from mpl_toolkits.mplot3d import proj3d

    class Arrow3D(FancyArrowPatch):
        def __init__(self, start, end, **kwargs) -> None:
            super().__init__((0.0, 0.0), (0.0, 0.0), **kwargs)
            self._xyz = (np.asarray(start, float), np.asarray(end, float))

        def do_3d_projection(self, renderer=None) -> float:
            ends = np.stack(self._xyz, axis=1)  # rows x, y, z; columns start, end
            xs, ys, zs = proj3d.proj_transform(*ends, self.axes.get_proj())  # type: ignore[union-attr]
            self.set_positions((xs[0], ys[0]), (xs[1], ys[1]))
            return float(np.min(zs))

    return Arrow3D


def _view_azimuth(rel: NDArray[np.float64], forces: NDArray[np.float64], elev_deg: float) -> float:
    """Azimuth [deg] from which the fingers and their force arrows are best seen.

    ``rel`` are the fingertip centres relative to the object centre, ``forces`` the finger forces.
    The score favours views that keep the fingertips apart on the image, show every force arrow
    with little foreshortening, and keep the fingertips on the viewer's side of the object.
    """
    a_deg = np.arange(0.0, 360.0, 2.0)
    # Skip views along a coordinate axis: one axis would collapse to a point with its tick labels.
    a = np.deg2rad(a_deg[np.abs((a_deg + 45.0) % 90.0 - 45.0) >= 12.0])
    e = np.deg2rad(elev_deg)
    eye = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.full_like(a, np.sin(e))], axis=1)
    right = np.stack([-np.sin(a), np.cos(a), np.zeros_like(a)], axis=1)
    up = np.cross(eye, right)
    size = float(np.linalg.norm(rel, axis=1).max()) or 1.0
    screen = np.stack([rel @ right.T, rel @ up.T], axis=-1) / size  # (n_f, A, 2)
    depth = rel @ eye.T / size  # (n_f, A)
    score = 0.3 * depth.min(axis=0)
    if rel.shape[0] > 1:
        iu = np.triu_indices(rel.shape[0], 1)
        gaps = np.linalg.norm(screen[iu[0]] - screen[iu[1]], axis=-1)  # (pairs, A)
        score += np.minimum(gaps.min(axis=0), 0.8)
    fn = np.linalg.norm(forces, axis=1)
    if (fn > 0).any():
        u = forces[fn > 0] / fn[fn > 0, None]
        along = u @ eye.T  # cos of the angle between each arrow and the line of sight
        score += 0.8 * np.sqrt(np.clip(1.0 - along**2, 0.0, 1.0)).min(axis=0)
    return float(np.rad2deg(a[int(np.argmax(score))]))


def plot_grasp_3d(
    points: NDArray[np.float64],
    facets: NDArray[np.int64],
    centres: NDArray[np.float64],
    radii: NDArray[np.float64],
    forces: NDArray[np.float64],
    contact_points: NDArray[np.float64],
    names: Sequence[str],
    path: str | Path,
    title: str = "",
    weight: tuple[NDArray[np.float64], float] | None = None,
    *,
    elev: float = 20.0,
    azim: float | None = None,
    links: Sequence[NDArray[np.float64]] = (),
    setpoints: Sequence[float] | None = None,
) -> Path:
    """3D picture of a grasp: deformed object surface, fingertip spheres and contact force arrows.

    Parameters
    ----------
    points: node positions [m] of the (deformed) object, shape (N, 3).
    facets: boundary triangles (node indices, outward right-hand normals), shape (F, 3).
    centres: fingertip sphere centres [m], shape (n_f, 3).
    radii: fingertip radii [m], shape (n_f,).
    forces: force [N] of each finger on the object, shape (n_f, 3); drawn as an arrow starting at the
        contact point. Arrow lengths share one scale, chosen so the largest arrow (weight included)
        is 40 % of the object's largest extent; the scale is given in the legend.
    contact_points: contact points [m], shape (n_f, 3).
    names: one label per finger.
    path: PNG file to write.
    title: figure title (none if empty).
    weight: optional (centre of mass [m] (3,), weight [N]) drawn as a downward arrow.
    elev, azim: viewpoint [deg]; by default the azimuth is chosen so all fingers are visible.
    links: the hand drawn as polylines [m], each (K, 3) (palm outline, finger joints to tip).
    setpoints: each finger's normal-force set-point [N], named in the legend beside the finger's
        |force| in the picture (a held state's forces are not the set-points).

    Raises
    ------
    ValueError: wrong shapes, non-finite values, bad facet indices, non-positive radii, a negative
        weight or a wrong number of names.
    """
    pts = as_array("points", points, (None, 3))
    if pts.shape[0] == 0:
        raise ValueError("points is empty")
    tri = np.asarray(facets)
    if tri.ndim != 2 or tri.shape[1] != 3 or tri.shape[0] == 0:
        raise ValueError(f"facets must have shape (F, 3) with F >= 1, got {tri.shape}")
    if not np.issubdtype(tri.dtype, np.integer):
        raise ValueError(f"facets must hold integer node indices, got dtype {tri.dtype}")
    if tri.min() < 0 or tri.max() >= pts.shape[0]:
        raise ValueError(f"facets refer to node indices outside 0..{pts.shape[0] - 1}")
    c = as_array("centres", centres, (None, 3))
    n_f = c.shape[0]
    r = as_array("radii", radii, (n_f,))
    if (r <= 0).any():
        raise ValueError(f"radii must be > 0 m, got {r.tolist()}")
    f = as_array("forces", forces, (n_f, 3))
    cp = as_array("contact_points", contact_points, (n_f, 3))
    names = check_names(names, n_f)
    sp = None if setpoints is None else as_array("setpoints", setpoints, (n_f,))
    com = None
    w = 0.0
    if weight is not None:
        if len(weight) != 2:
            raise ValueError("weight must be a pair (centre of mass (3,) [m], weight [N])")
        com = as_array("weight centre of mass", weight[0], (3,))
        w = float(weight[1])
        if not (np.isfinite(w) and w >= 0):
            raise ValueError(f"weight must be a finite force >= 0 N, got {w}")

    # Everything below in millimetres.
    P, C, R, CP = 1e3 * pts, 1e3 * c, 1e3 * r, 1e3 * cp
    used = P[np.unique(tri)]
    lo, hi = used.min(axis=0), used.max(axis=0)
    centre = 0.5 * (lo + hi)
    size = float((hi - lo).max()) or float(2 * R.max())
    norms = np.linalg.norm(f, axis=1)
    f_max = max(float(norms.max()) if n_f else 0.0, w)
    if sp is None:
        labels = [f"{names[i]}: {norms[i]:.2f} N" for i in range(n_f)]
    else:
        labels = [f"{names[i]}: |F| {norms[i]:.2f} N, set-point {sp[i]:.3f} N" for i in range(n_f)]
    mm_per_N = 0.4 * size / f_max if f_max > 0 else 0.0

    if azim is None:
        azim = _view_azimuth(C - centre, f, elev) if n_f else -60.0

    plt = pyplot()
    from matplotlib.lines import Line2D
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    Arrow3D = _arrow3d_class()
    fig = plt.figure(figsize=(7.0, 6.4), dpi=120)
    ax = fig.add_subplot(projection="3d", computed_zorder=False)
    ax.view_init(elev=elev, azim=azim)

    e, a = np.deg2rad(elev), np.deg2rad(azim)
    eye = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    right = np.array([-np.sin(a), np.cos(a), 0.0])
    up = np.cross(eye, right)
    light = eye + 0.6 * up - 0.5 * right  # from above-left of the viewer
    light /= np.linalg.norm(light)

    def shade(
        normals: NDArray[np.float64], rgb: NDArray[np.float64], alpha: float | NDArray[np.float64]
    ) -> NDArray[np.float64]:
        lam = np.clip(normals @ light, 0.0, 1.0)
        k = (0.45 + 0.55 * lam)[:, None]
        out = np.empty((normals.shape[0], 4))
        out[:, :3] = np.clip(k * rgb[None, :], 0.0, 1.0)
        out[:, 3] = alpha
        return out

    # Object surface.
    tris = P[tri]
    nrm = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
    obj_rgb = np.array([0.80, 0.74, 0.62])
    # Facets facing the viewer are half opaque, those on the far side faint: a solid look that
    # still shows the fingertips and arrows behind or inside the object.
    front = nrm @ eye >= 0.0
    edges = np.tile([0.35, 0.30, 0.25, 0.0], (tri.shape[0], 1))
    edges[:, 3] = np.where(front, 0.3, 0.08)
    surface = Poly3DCollection(
        tris,
        facecolors=shade(nrm, obj_rgb, np.where(front, 0.5, 0.15)),
        edgecolors=edges,
        linewidths=0.3 if tri.shape[0] < 1500 else 0.2,
        zorder=2,
    )
    ax.add_collection3d(surface)

    # Fingertip spheres: those behind the object centre are drawn first, seen through the surface.
    from matplotlib.colors import to_rgb

    u = np.linspace(0.0, 2 * np.pi, 25)
    v = np.linspace(0.0, np.pi, 13)
    unit = np.stack(
        [
            np.outer(np.cos(u), np.sin(v)),
            np.outer(np.sin(u), np.sin(v)),
            np.outer(np.ones_like(u), np.cos(v)),
        ],
        axis=-1,
    )  # (25, 13, 3)
    quads = np.stack([unit[:-1, :-1], unit[1:, :-1], unit[1:, 1:], unit[:-1, 1:]], axis=2).reshape(-1, 4, 3)
    quad_n = quads.mean(axis=1)
    quad_n /= np.linalg.norm(quad_n, axis=1, keepdims=True)
    handles = []
    for i in range(n_f):
        colour, _ = finger_style(i)
        behind = float((C[i] - centre) @ eye) < 0
        ax.add_collection3d(
            Poly3DCollection(
                C[i] + R[i] * quads,
                facecolors=shade(quad_n, np.array(to_rgb(colour)), 0.95),
                edgecolors="none",
                zorder=1 if behind else 3,
            )
        )
        handles.append(Line2D([], [], ls="-", lw=2.2, color=colour, marker="o", ms=9, label=labels[i]))

    # Force arrows (on top of everything) with one shared scale.
    ends = [P[np.unique(tri)], (C - R[:, None]), (C + R[:, None])]
    for k, line in enumerate(links):
        L = 1e3 * as_array(f"links[{k}]", line, (None, 3))
        ends.append(L)
        ax.plot(*L.T, color="0.35", lw=3.0, marker="o", ms=3.5, solid_capstyle="round", zorder=4)
    if len(links):
        handles.append(Line2D([], [], color="0.35", lw=3.0, marker="o", ms=3.5, label="hand"))
    from matplotlib.patheffects import Normal, Stroke

    # A white halo keeps each arrow readable over its own fingertip and over the surface edges.
    arrow_style = dict(
        arrowstyle="-|>",
        mutation_scale=16,
        lw=2.6,
        zorder=5,
        path_effects=[Stroke(linewidth=4.6, foreground="white", alpha=0.9), Normal()],
    )
    if mm_per_N > 0:
        for i in range(n_f):
            if norms[i] <= 0:
                continue
            colour, _ = finger_style(i)
            end = CP[i] + mm_per_N * f[i]
            ends.append(np.stack([CP[i], end]))
            ax.add_artist(Arrow3D(CP[i], end, color=colour, **arrow_style))
            ax.scatter(*CP[i], s=14, color="k", depthshade=False, zorder=6)
        if com is not None and w > 0:
            G = 1e3 * com
            end = G + np.array([0.0, 0.0, -mm_per_N * w])
            ends.append(np.stack([G, end]))
            ax.add_artist(Arrow3D(G, end, color="k", **arrow_style))
            ax.scatter(*G, s=18, color="k", depthshade=False, zorder=6)
            handles.append(
                Line2D([], [], color="k", lw=2.2, marker=r"$\downarrow$", ms=10, label=f"weight: {w:.2f} N")
            )
        handles.append(
            Line2D(
                [],
                [],
                ls="none",
                marker=r"$\rightarrow$",
                ms=12,
                color="0.3",
                label=f"force on object (arrow: 1 N = {mm_per_N:.3g} mm)",
            )
        )

    # Equal aspect: limits from everything drawn, box aspect from their ranges.
    allp = np.concatenate(ends, axis=0)
    lo, hi = allp.min(axis=0), allp.max(axis=0)
    pad = 0.04 * float((hi - lo).max() or 1.0)
    lo, hi = lo - pad, hi + pad
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_zlim(lo[2], hi[2])
    ax.set_box_aspect(tuple(hi - lo), zoom=1.0)
    ax.set_xlabel("x [mm]", labelpad=6)
    ax.set_ylabel("y [mm]", labelpad=6)
    ax.set_zlabel("z [mm]", labelpad=6)
    ax.tick_params(labelsize=8, pad=1)
    # The 3D axes leave wide margins inside their area: put the title and legend against the box
    # actually drawn, and let the tight bounding box crop the rest.
    renderer = fig.canvas.get_renderer()
    fig.draw_without_rendering()
    from matplotlib.transforms import Bbox
    from mpl_toolkits.mplot3d import proj3d

    corners = np.array(np.meshgrid(*zip(lo, hi, strict=True), indexing="ij")).reshape(3, -1)
    xs, ys, _ = proj3d.proj_transform(*corners, ax.get_proj())
    drawn = [
        Bbox.from_extents(
            *ax.transData.transform((min(xs), min(ys))), *ax.transData.transform((max(xs), max(ys)))
        )
    ]
    drawn += [a.get_tightbbox(renderer) for a in (ax.xaxis, ax.yaxis, ax.zaxis)]
    box = Bbox.union([b for b in drawn if b is not None and np.isfinite(b.bounds).all()])
    fbox = box.transformed(fig.transFigure.inverted())
    extra = []
    if title:
        extra.append(
            fig.text(0.5 * (fbox.x0 + fbox.x1), fbox.y1 + 0.01, title, ha="center", va="bottom", fontsize=12)
        )
    extra.append(
        fig.legend(
            handles=handles,
            loc="upper center",
            bbox_to_anchor=(0.5 * (fbox.x0 + fbox.x1), fbox.y0 - 0.005),
            ncol=2,
            frameon=False,
            fontsize=9,
        )
    )
    fig.draw_without_rendering()
    crop = Bbox.union([box, *(a.get_window_extent(renderer) for a in extra)])
    crop = crop.padded(0.12 * fig.dpi).transformed(fig.dpi_scale_trans.inverted())  # inches
    out = atomic_write(path, lambda p: fig.savefig(p, format="png", bbox_inches=crop))
    plt.close(fig)
    return out
