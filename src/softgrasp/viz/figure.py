"""What every softgrasp figure shares: pyplot on the Agg backend, the finish of a curve plot
(grid, axes from the origin, legend), the atomic PNG write, the finger colours and markers and the
checks of figure inputs."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from softgrasp.io.atomic import atomic_write

__all__ = [
    "FINGER_COLOURS",
    "FINGER_MARKERS",
    "as_array",
    "check_names",
    "finger_style",
    "pyplot",
    "save_curve",
    "write_png",
]


def pyplot():
    """``matplotlib.pyplot`` on the non-interactive Agg backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def write_png(plt, fig, path: str | Path) -> Path:
    """Lay the figure out, write it as a PNG atomically (no half-written file) and close it."""
    fig.tight_layout()
    out = atomic_write(path, lambda p: fig.savefig(p, format="png"))
    plt.close(fig)
    return out


def save_curve(
    plt, fig, ax, path: str | Path, legend_loc: str = "best", *, x_from_zero: bool = True, legend: bool = True
) -> Path:
    """Common finish of softgrasp's curves: grid, axes from the origin (x optionally not), legend,
    atomic PNG."""
    ax.grid(alpha=0.3)
    if x_from_zero:
        ax.set_xlim(left=0)
    ax.set_ylim(bottom=0)
    if legend:
        ax.legend(frameon=False, loc=legend_loc)
    return write_png(plt, fig, path)


#: Colour of finger i in every planner figure (thumb, first, middle, then more).
FINGER_COLOURS = (
    "tab:red",
    "tab:blue",
    "tab:green",
    "tab:purple",
    "tab:orange",
    "tab:brown",
    "tab:pink",
    "tab:olive",
    "tab:cyan",
)
FINGER_MARKERS = ("o", "s", "^", "D", "v", "P", "X", "<", ">")


def finger_style(i: int) -> tuple[str, str]:
    """Colour and marker of finger ``i`` (cycled beyond the palette)."""
    return FINGER_COLOURS[i % len(FINGER_COLOURS)], FINGER_MARKERS[i % len(FINGER_MARKERS)]


def as_array(what: str, value: object, shape: tuple[int | None, ...]) -> NDArray[np.float64]:
    """``value`` as a finite float array of ``shape`` (``None`` = any length), else ValueError."""
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{what} must be numeric, got {type(value).__name__}") from exc
    want = (
        "(" + ", ".join("n" if s is None else str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"
    )
    if a.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, a.shape, strict=True)):
        raise ValueError(f"{what} must have shape {want}, got {a.shape}")
    if not np.isfinite(a).all():
        raise ValueError(f"{what} holds NaN or infinite values")
    return a


def check_names(names: Sequence[str], n_f: int) -> list[str]:
    """``names`` as strings, one per finger of the data (``n_f``), else ValueError."""
    names = [str(n) for n in names]
    if len(names) != n_f:
        raise ValueError(f"names has {len(names)} entries but the data has {n_f} fingers")
    return names
