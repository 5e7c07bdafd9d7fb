"""Figures of the material experiments: compression stress-strain curves, indentation
force-penetration curves and the measured-vs-fitted curves of a calibration."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from softgrasp.viz.figure import pyplot, save_curve

__all__ = ["plot_calibration", "plot_force_penetration", "plot_stress_strain"]


def plot_stress_strain(
    path: str | Path,
    strain: NDArray[np.float64],
    stress_Pa: NDArray[np.float64],
    *,
    apparent_E_Pa: float,
    title: str,
    linear_E_Pa: float | None = None,
) -> Path:
    """Stress-strain curve of a compression test (paper Fig. 9 style): stress in kPa vs strain in %.

    Also draws the initial-slope line and, if given, the linear-elastic line of the material's E.
    """
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4.4), dpi=120)
    ax.plot(100 * strain, stress_Pa / 1e3, "o-", ms=3.5, lw=1.6, label="softgrasp simulation")
    e = np.linspace(0, float(strain.max()), 50)
    ax.plot(
        100 * e,
        apparent_E_Pa * e / 1e3,
        "--",
        lw=1.0,
        color="0.4",
        label=f"initial slope {apparent_E_Pa / 1e3:.4g} kPa",
    )
    if linear_E_Pa is not None:
        ax.plot(
            100 * e,
            linear_E_Pa * e / 1e3,
            ":",
            lw=1.0,
            color="tab:red",
            label=f"material E = {linear_E_Pa / 1e3:.4g} kPa",
        )
    ax.set_xlabel("compressive strain [%]")
    ax.set_ylabel("nominal stress [kPa]")
    ax.set_title(title)
    out = save_curve(plt, fig, ax, path)
    return out


def plot_force_penetration(
    path: str | Path,
    penetration_m: NDArray[np.float64],
    force_N: NDArray[np.float64],
    *,
    title: str,
    measured: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None,
    mean_abs_error_N: float | None = None,
) -> Path:
    """Force against penetration of an indentation test (paper Fig. 11 style): N vs mm.

    Parameters
    ----------
    path: PNG file to write.
    penetration_m: simulated penetrations [m], (K,).
    force_N: simulated fingertip forces [N], (K,).
    title: figure title.
    measured: optional measured (penetration [m], force [N]) drawn as markers.
    mean_abs_error_N: mean absolute force error [N] shown in the legend with the measurements.
    """
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4.4), dpi=120)
    ax.plot(1e3 * penetration_m, force_N, "o-", ms=3.0, lw=1.6, label="softgrasp simulation")
    if measured is not None:
        label = "measured"
        if mean_abs_error_N is not None:
            label += f" (mean |error| {mean_abs_error_N:.3g} N)"
        ax.plot(
            1e3 * measured[0],
            measured[1],
            "s",
            ms=5.0,
            mfc="none",
            mew=1.3,
            color="tab:red",
            label=label,
        )
    ax.set_xlabel("penetration [mm]")
    ax.set_ylabel("force [N]")
    ax.set_title(title)
    out = save_curve(plt, fig, ax, path, legend_loc="upper left")
    return out


def plot_calibration(
    path: str | Path,
    x_m: NDArray[np.float64],
    measured_N: NDArray[np.float64],
    fitted_N: NDArray[np.float64],
    *,
    xlabel: str,
    title: str,
    summary: str,
    lateral: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None,
) -> Path:
    """Measured vs fitted force (N vs mm) of a calibration; with lateral strains (measured,
    fitted) a second panel shows them (in %).

    Parameters
    ----------
    path: PNG file to write.
    x_m: displacement or penetration [m], (P,).
    measured_N, fitted_N: forces [N], (P,).
    xlabel: the abscissa's name (the unit [mm] is appended).
    title: figure title.  summary: the fitted values, shown under the legend.
    lateral: optional (measured, fitted) lateral strains, (P,) each.
    """
    plt = pyplot()
    ncols = 2 if lateral is not None else 1
    fig, axes = plt.subplots(1, ncols, figsize=(6.4 * ncols, 4.6), dpi=120, squeeze=False)
    ax = axes[0, 0]
    ax.plot(1e3 * x_m, measured_N, "s", ms=4.0, mfc="none", mew=1.2, color="tab:red", label="measured")
    ax.plot(1e3 * x_m, fitted_N, "-", lw=1.8, color="tab:blue", label="softgrasp, fitted")
    ax.set_xlabel(f"{xlabel} [mm]")
    ax.set_ylabel("force [N]")
    ax.text(0.03, 0.72, summary, transform=ax.transAxes, fontsize=8.5, va="top", family="monospace")
    ax.set_title(title)
    if lateral is not None:
        ax2 = axes[0, 1]
        ax2.plot(
            1e3 * x_m, 100 * lateral[0], "s", ms=4.0, mfc="none", mew=1.2, color="tab:red", label="measured"
        )
        ax2.plot(1e3 * x_m, 100 * lateral[1], "-", lw=1.8, color="tab:blue", label="softgrasp, fitted")
        ax2.set_xlabel(f"{xlabel} [mm]")
        ax2.set_ylabel("lateral strain [%]")
        ax2.set_title("lateral strain (widening)")
        ax2.grid(alpha=0.3)
        ax2.set_xlim(left=0)
        ax2.legend(frameon=False, loc="upper left")
    return save_curve(plt, fig, ax, path, legend_loc="upper left")
