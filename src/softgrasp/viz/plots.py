"""Matplotlib figures written as PNG files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from softgrasp.output import atomic_write

__all__ = ["plot_force_penetration", "plot_stress_strain"]


def _figure():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(plt, fig, ax, path: str | Path, legend_loc: str = "best") -> Path:
    """Common finish of softgrasp's curves: grid, axes from the origin, legend, atomic PNG."""
    ax.grid(alpha=0.3)
    ax.set_xlim(left=0)
    ax.set_ylim(bottom=0)
    ax.legend(frameon=False, loc=legend_loc)
    fig.tight_layout()
    out = atomic_write(path, lambda p: fig.savefig(p, format="png"))
    plt.close(fig)
    return out


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
    plt = _figure()
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
    out = _save(plt, fig, ax, path)
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
    plt = _figure()
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
    out = _save(plt, fig, ax, path, legend_loc="upper left")
    return out
