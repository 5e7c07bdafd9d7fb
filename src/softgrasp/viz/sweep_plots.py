"""Figures of parameter sweeps and robust planning: set-points against a swept parameter, the
success map over two parameters, and the robust set-points against the uncertain parameters."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from softgrasp.viz.figure import finger_style, pyplot, save_curve, write_png

__all__ = ["plot_robust", "plot_success_map", "plot_sweep_forces"]

_AXIS_LABELS = {
    "mu": ("friction coefficient mu", 1.0),
    "E": ("Young's modulus E [kPa]", 1e-3),
    "nu": ("Poisson's ratio nu", 1.0),
    "fingertip_radius": ("fingertip radius [mm]", 1e3),
    "mesh_size": ("mesh size [mm]", 1e3),
    "safety_factor": ("safety factor", 1.0),
    "mass": ("mass [g]", 1e3),
    "density": ("density [kg/m^3]", 1.0),
}


def _axis(name: str) -> tuple[str, float]:
    return _AXIS_LABELS.get(name, (name, 1.0))


def plot_sweep_forces(
    path: str | Path,
    values: NDArray[np.float64],
    setpoints: NDArray[np.float64],
    names: Sequence[str],
    *,
    parameter: str,
    title: str,
    failed: NDArray[np.float64] | None = None,
) -> Path:
    """Set-points of every finger against one swept parameter: each case a marker; on a grid
    (repeated values) the mean over the cases at each value as a line (other parameters vary within
    a value's cases); a random sample has markers only (its spread is the other parameters').

    Parameters
    ----------
    values: the parameter of each successful case (SI), (C,).
    setpoints: the finger set-points [N] of those cases, (C, F).
    names: finger names.  parameter: the swept option (sets the axis label and unit).
    failed: the parameter's values of the failed cases, marked on the axis.
    """
    plt = pyplot()
    label, scale = _axis(parameter)
    fig, ax = plt.subplots(figsize=(6.4, 4.4), dpi=120)
    x = np.asarray(values, dtype=np.float64) * scale
    ux = np.unique(x)
    grid = len(ux) <= len(x) / 2  # repeated values (a grid): their mean as a line
    for j, n in enumerate(names):
        colour, marker = finger_style(j)
        ax.plot(
            x,
            setpoints[:, j],
            marker,
            ls="none",
            color=colour,
            ms=4.0 if grid else 5.5,
            alpha=0.45 if grid else 0.85,
            label=None if grid else n,
        )
        if grid:
            ax.plot(ux, [setpoints[x == u, j].mean() for u in ux], "-", color=colour, lw=1.8, label=n)
    if failed is not None and len(failed):
        ax.plot(
            np.asarray(failed) * scale, np.zeros(len(failed)), "x", color="k", ms=7, label="no plan (failed)"
        )
    ax.set_xlabel(label)
    ax.set_ylabel("set-point (normal force) [N]")
    ax.set_title(title)
    return save_curve(plt, fig, ax, path, x_from_zero=False)


def plot_success_map(
    path: str | Path,
    x: NDArray[np.float64],
    y: NDArray[np.float64],
    ok: NDArray[np.bool_],
    total_N: NDArray[np.float64],
    *,
    x_name: str,
    y_name: str,
    title: str,
) -> Path:
    """Success map over two swept parameters: planned cases coloured by their total set-point
    [N], cases without a plan (failed) as crosses."""
    plt = pyplot()
    (xl, xs), (yl, ys) = _axis(x_name), _axis(y_name)
    fig, ax = plt.subplots(figsize=(6.4, 4.8), dpi=120)
    x, y, ok = np.asarray(x) * xs, np.asarray(y) * ys, np.asarray(ok, dtype=bool)
    if ok.any():
        sc = ax.scatter(x[ok], y[ok], c=np.asarray(total_N)[ok], cmap="viridis", s=70, edgecolors="k", lw=0.5)
        fig.colorbar(sc, ax=ax, label="sum of the set-points [N]")
    if (~ok).any():
        ax.scatter(x[~ok], y[~ok], marker="x", c="tab:red", s=70, lw=2.0, label="no plan (failed)")
        ax.legend(frameon=False, loc="best")
    ax.set_xlabel(xl)
    ax.set_ylabel(yl)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    return write_png(plt, fig, path)


def plot_robust(
    path: str | Path,
    parameters: dict[str, NDArray[np.float64]],
    required_total: NDArray[np.float64],
    nominal_held: NDArray[np.bool_],
    *,
    robust_total: float,
    nominal_total: float,
    title: str,
) -> Path:
    """Robust set-points against the uncertain parameters: one panel per parameter, each sample's
    required total set-point (sum over the fingers) as a marker, filled where the nominal plan's
    set-points held that sample and a cross where they did not, with the robust and the nominal
    totals as lines.

    Parameters
    ----------
    parameters: each uncertain parameter's sampled values (SI), (S,) each.
    required_total: each sample's planned total set-point [N], (S,) (inf: cannot be held).
    nominal_held: whether the nominal set-points held each sample, (S,).
    robust_total, nominal_total: sums of the robust and nominal set-points [N].
    """
    plt = pyplot()
    names = list(parameters)
    fig, axes = plt.subplots(1, len(names), figsize=(4.6 * len(names) + 0.6, 4.4), dpi=120, squeeze=False)
    ok = np.isfinite(required_total)
    held = np.asarray(nominal_held, dtype=bool)
    for k, (ax, name) in enumerate(zip(axes[0], names, strict=True)):
        label, scale = _axis(name)
        x = np.asarray(parameters[name], dtype=np.float64) * scale
        ax.plot(
            x[ok & held],
            required_total[ok & held],
            "o",
            color="#2a9d8f",
            ms=5.5,
            label="nominal set-points held",
        )
        ax.plot(
            x[ok & ~held],
            required_total[ok & ~held],
            "x",
            color="#d62828",
            ms=6.5,
            mew=1.6,
            label="nominal set-points failed",
        )
        ax.axhline(robust_total, color="#264653", lw=1.8, label=f"robust: {robust_total:.3g} N")
        ax.axhline(nominal_total, color="0.45", lw=1.3, ls="--", label=f"nominal: {nominal_total:.3g} N")
        ax.set_xlabel(label)
        if k == 0:
            ax.set_ylabel("total set-point the sample needs [N]")
        ax.grid(alpha=0.3)
        ax.set_ylim(bottom=0, top=1.15 * max(robust_total, float(np.max(required_total[ok], initial=0.0))))
    axes[0][0].legend(frameon=False, loc="lower left", fontsize=8)
    fig.suptitle(title)
    return write_png(plt, fig, path)
