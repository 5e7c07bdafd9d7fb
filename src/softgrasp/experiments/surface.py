"""The top of an object's surface under a point seen from above: where a fingertip pressing
straight down lands (:func:`softgrasp.experiments.indentation.indentation_test`)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from softgrasp.errors import ConfigError

__all__ = ["surface_height"]


def _upward_facets(x: NDArray[np.float64], facets: NDArray[np.int64], xy: NDArray[np.float64]):
    """Upward-facing facets whose xy projection contains ``xy``, with the interpolated heights."""
    tri = x[facets]
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    nz = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    up = nz > 0  # twice the signed projected area: > 0 for an outward normal with a +z component
    a, b, c, nz = a[up], b[up], c[up], nz[up]
    idx = np.flatnonzero(up)
    px, py = float(xy[0]), float(xy[1])
    lb = ((c[:, 0] - px) * (a[:, 1] - py) - (c[:, 1] - py) * (a[:, 0] - px)) / nz
    lc = ((a[:, 0] - px) * (b[:, 1] - py) - (a[:, 1] - py) * (b[:, 0] - px)) / nz
    la = 1.0 - lb - lc
    lam = np.stack([la, lb, lc], axis=1)
    inside = (lam >= -1e-9).all(axis=1)
    z = la * a[:, 2] + lb * b[:, 2] + lc * c[:, 2]
    return idx[inside], z[inside]


def surface_height(
    x: NDArray[np.float64], facets: NDArray[np.int64], xy: Sequence[float] | NDArray[np.float64]
) -> tuple[float, int]:
    """Height [m] of the top of the surface under the point ``xy`` [m], and the facet it lies on.

    Parameters
    ----------
    x: node positions [m], (N, 3).
    facets: boundary facets with outward ordering, (F, 3).
    xy: the point (x, y) [m].

    Raises
    ------
    ConfigError: no upward-facing boundary facet lies above or below the point (it is outside the
        object's outline seen from above).
    """
    p = np.asarray(xy, dtype=np.float64)
    idx, z = _upward_facets(x, facets, p)
    if idx.size == 0:
        lo, hi = x[:, :2].min(axis=0), x[:, :2].max(axis=0)
        raise ConfigError(
            f"press point ({p[0] * 1e3:.2f}, {p[1] * 1e3:.2f}) mm is not above the object "
            f"(its outline spans x {lo[0] * 1e3:.1f}..{hi[0] * 1e3:.1f} mm, "
            f"y {lo[1] * 1e3:.1f}..{hi[1] * 1e3:.1f} mm)"
        )
    k = int(np.argmax(z))
    return float(z[k]), int(idx[k])
