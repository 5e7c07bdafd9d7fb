"""Figures of an executed grasp (MuJoCo): measured normal forces against time with the
set-points, and the pictures of the scene at the execution's events, each titled by its event
and the run's outcome: MuJoCo's own renderings (:func:`save_execution_image`) or, where MuJoCo
cannot render, matplotlib's drawing of the hand's snapshot (:func:`plot_execution_frame`)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from softgrasp.io.atomic import atomic_write
from softgrasp.viz.figure import as_array, check_names, finger_style, pyplot, save_curve
from softgrasp.viz.grasp_plots import plot_grasp_3d

__all__ = [
    "EXECUTION_FRAME_TITLES",
    "execution_frame_title",
    "plot_execution_forces",
    "plot_execution_frame",
    "save_execution_image",
    "write_execution_pictures",
]

#: The execution's pictures: event -> what it shows (paper Fig. 14: initial pose, contact,
#: deformation; then the end of the hold).
EXECUTION_FRAME_TITLES = {
    "start": "initial pose",
    "contact": "first contact",
    "closed": "closed",
    "end": "after the lift and hold",
}

#: Height [pixels] of the title band over a rendered picture.
TITLE_BAND = 56


def execution_frame_title(
    event: str, t_s: float, *, reached: bool, lifted: bool, rise_m: float, lift_m: float
) -> str:
    """The two-line title of the picture of ``event`` at time ``t_s`` [s]: what it shows, then
    the run's outcome (set-points reached or not; lifted, or dropped, with the rise [m] of the
    ``lift_m`` [m] lift). The last picture says "lifted" only when the object was held."""
    what = EXECUTION_FRAME_TITLES.get(event, event)
    if event == "closed":
        what = "closed to the set-points" if reached else "closing ended short of the set-points"
    elif event == "end":
        what = "lifted and held" if lifted else "dropped"
    outcome = "lifted" if lifted else "dropped"
    return (
        f"{what} (t = {t_s:.2f} s, MuJoCo)\n"
        f"run: {outcome}, rose {round(rise_m * 1e3, 1) + 0.0:.1f} of {lift_m * 1e3:.0f} mm; "
        f"set-points {'reached' if reached else 'not reached'}"
    )


def save_execution_image(path: str | Path, image: NDArray[np.uint8], title: str) -> Path:
    """Write ``image`` (RGB, (H, W, 3), as MuJoCo rendered it) as a PNG with ``title`` in a band
    of :data:`TITLE_BAND` pixels above it: W x (H + band) pixels, the image unscaled."""
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise ValueError(f"image must be RGB (H, W, 3) uint8, got {img.shape} {img.dtype}")
    h, w = img.shape[:2]
    dpi = 100
    plt = pyplot()
    fig = plt.figure(figsize=(w / dpi, (h + TITLE_BAND) / dpi), dpi=dpi)
    ax = fig.add_axes((0.0, 0.0, 1.0, h / (h + TITLE_BAND)))
    ax.imshow(img, interpolation="nearest")
    ax.set_axis_off()
    fig.text(0.5, 1.0 - 0.5 * TITLE_BAND / (h + TITLE_BAND), title, ha="center", va="center", fontsize=10)
    out = atomic_write(path, lambda p: fig.savefig(p, format="png", dpi=dpi))
    plt.close(fig)
    return out


def plot_execution_frame(
    path: str | Path,
    frame: tuple,
    facets: NDArray[np.int64],
    names: Sequence[str],
    radius: float,
    title: str,
) -> Path:
    """One picture of the executed grasp drawn by matplotlib from a hand's snapshot (nodes,
    fingertip centres, forces on the object, hand polylines, time), titled ``title``; the contact
    drawn on each fingertip's side facing the object (along its force on the object). The
    stand-in for :func:`save_execution_image` where MuJoCo cannot render."""
    nodes, tips, forces, links, _ = frame
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
        title=title,
        links=links,
    )


def write_execution_pictures(
    out: str | Path,
    prefix: str,
    *,
    images: Mapping[str, NDArray[np.uint8]],
    snapshots: Mapping[str, tuple],
    times: Mapping[str, float],
    facets: NDArray[np.int64],
    names: Sequence[str],
    radius: float,
    reached: bool,
    lifted: bool,
    rise_m: float,
    lift_m: float,
) -> list[str]:
    """Write the picture of each event of an execution into ``out`` as ``<prefix><event>.png``
    titled by :func:`execution_frame_title`: MuJoCo's rendering (``images``) or, for an event
    without one, matplotlib's drawing of the hand's snapshot (``snapshots``, with the object's
    surface ``facets``, finger ``names`` and fingertip ``radius`` [m]); return the files' names.

    times: the hand's time [s] at each event.  reached, lifted, rise_m, lift_m: the run's outcome.
    """
    written = []
    for event in EXECUTION_FRAME_TITLES:
        if event not in images and event not in snapshots:
            continue
        name = f"{prefix}{event}.png"
        t = times[event] if event in times else float(snapshots[event][4])
        title = execution_frame_title(event, t, reached=reached, lifted=lifted, rise_m=rise_m, lift_m=lift_m)
        if event in images:
            save_execution_image(Path(out) / name, images[event], title)
        else:
            plot_execution_frame(Path(out) / name, snapshots[event], facets, names, radius, title)
        written.append(name)
    return written


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
        ax.plot(x, f[:, i], lw=1.4, color=colour, label=f"{name} (set-point {sp[i]:.3g} N)")
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
