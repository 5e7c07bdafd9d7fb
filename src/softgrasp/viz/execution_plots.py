"""Figures of an executed grasp (MuJoCo): measured normal forces against time with the
set-points, and pictures of the hand and object at the execution's events."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from softgrasp.viz.figure import as_array, check_names, finger_style, pyplot, save_curve
from softgrasp.viz.grasp_plots import plot_grasp_3d

__all__ = ["EXECUTION_FRAME_TITLES", "plot_execution_forces", "plot_execution_frame"]

#: The execution's pictures: event -> title (paper Fig. 14: initial pose, contact, deformation).
EXECUTION_FRAME_TITLES = {
    "start": "initial pose",
    "contact": "first contact",
    "closed": "final deformation",
    "end": "lifted",
}


def plot_execution_frame(
    path: str | Path,
    frame: tuple,
    facets: NDArray[np.int64],
    names: Sequence[str],
    radius: float,
    event: str,
) -> Path:
    """One picture of the executed grasp from a hand's snapshot (nodes, fingertip centres, forces
    on the object, hand polylines, time); the contact drawn on each fingertip's side facing the
    object (along its force on the object)."""
    nodes, tips, forces, links, t_ev = frame
    unit = np.nan_to_num(forces / np.maximum(np.linalg.norm(forces, axis=1, keepdims=True), 1e-12))
    return plot_grasp_3d(
        nodes,
        facets,
        tips,
        np.full(len(names), radius),
        forces,
        tips + radius * unit,
        names,
        path,
        title=f"{EXECUTION_FRAME_TITLES.get(event, event)} (t = {t_ev:.2f} s, MuJoCo)",
        links=links,
    )


def plot_execution_forces(
    t: NDArray[np.float64],
    forces: NDArray[np.float64],
    setpoints: Sequence[float],
    names: Sequence[str],
    path: str | Path,
    *,
    phases: Sequence[tuple[str, float]] = (),
    tolerance: float = 0.05,
    title: str = "Executed grasp: measured normal force vs set-point",
) -> Path:
    """Measured fingertip normal force against time with each finger's set-point and its
    tolerance band (paper Fig. 15 style), the phases marked by vertical lines.

    Parameters
    ----------
    t: times [s], (K,).  forces: measured normal force per finger [N], (K, n_f).
    setpoints: per finger [N].  names: one label per finger.  path: PNG file to write.
    phases: (label, start time [s]) of each phase.  tolerance: relative half-width of the band.
    """
    x = as_array("t", t, (None,))
    f = as_array("forces", forces, (x.shape[0], None))
    sp = as_array("setpoints", np.asarray(setpoints, dtype=np.float64), (f.shape[1],))
    names = check_names(names, f.shape[1])
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7.2, 4.4), dpi=120)
    for i, name in enumerate(names):
        colour, _ = finger_style(i)
        ax.plot(x, f[:, i], lw=1.4, color=colour, label=f"{name} (set-point {sp[i]:.2f} N)")
        ax.axhline(sp[i], color=colour, lw=1.0, ls="--")
        ax.axhspan(sp[i] * (1 - tolerance), sp[i] * (1 + tolerance), color=colour, alpha=0.12, lw=0)
    top = float(max(f.max(initial=0.0), sp.max()) * 1.25)
    for label, start in phases:
        ax.axvline(start, color="0.5", lw=0.8, ls=":")
        ax.text(start, top * 0.98, f" {label}", va="top", ha="left", fontsize=8, color="0.35")
    ax.set_ylim(0.0, top)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("normal force [N]")
    ax.set_title(title)
    return save_curve(plt, fig, ax, path, legend_loc="lower right")
