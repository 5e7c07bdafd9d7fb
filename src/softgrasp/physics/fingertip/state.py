"""The fingertip contact's state and per-fingertip report (paper Sec. 3, Algorithm 1)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from softgrasp.physics.fingertip.geometry import ContactPairs

__all__ = ["FingerState", "FingerReport"]


@dataclass(frozen=True)
class FingerState:
    """Contact state of all (fingertip, facet) pairs, arrays over (n_fingers, F).

    Attributes
    ----------
    active: pair in contact at the last update, bool.
    anchor: barycentric coordinates of the stick anchor X_a on the facet, a material point (the
        pair's contact point when it started), (n_f, F, 3).
    offset: the fingertip centre's position relative to the anchor when the pair was last in
        equilibrium with its stick (its start, or its last slip) [m], (n_f, F, 3): the stick
        displacement v of Eq. 16 is the tangential part of (c - X_a) - offset, how far the
        fingertip has moved over the material since.
    slip: accumulated slip displacement u [m], (n_f, F, 3).
    memory: each finger's weighted mean stick displacement at the last update [m], (n_f, 3).
    """

    active: NDArray[np.bool_]
    anchor: NDArray[np.float64]
    offset: NDArray[np.float64]
    slip: NDArray[np.float64]
    memory: NDArray[np.float64]


@dataclass(frozen=True)
class FingerReport:
    """Per-fingertip totals at one instant.

    Attributes
    ----------
    force: force of each fingertip on the object [N], (n_f, 3).
    moment: moment of those forces about each fingertip centre [N m], (n_f, 3).
    normal: sum of the normal force magnitudes [N], (n_f,).
    tangential: norm of the summed friction force [N], (n_f,).
    contacts: number of touched facets, (n_f,).
    depth: largest facet penetration delta [m], (n_f,).
    """

    force: NDArray[np.float64]
    moment: NDArray[np.float64]
    normal: NDArray[np.float64]
    tangential: NDArray[np.float64]
    contacts: NDArray[np.int64]
    depth: NDArray[np.float64]


@dataclass(frozen=True)
class _Eval:
    pairs: ContactPairs
    fn: NDArray[np.float64]  # weighted normal force magnitude per pair [N]
    ft: NDArray[np.float64]  # friction on the finger per pair [N], (k, 3)
    w: NDArray[np.float64]
    kt: NDArray[np.float64]
    stick: NDArray[np.float64]  # tangential stick displacement per pair [m], (k, 3)
    cap: NDArray[np.float64]
    slipping: NDArray[np.bool_]
    depth: NDArray[np.float64]  # penetration the pair's normal law is evaluated at [m], (k,)
    deep: NDArray[np.int64]  # the pair that penetration is measured on, (k,)
    elastic: NDArray[np.float64]  # the normal law's elastic force there, unweighted [N], (k,)
    slope: NDArray[np.float64]  # its derivative d F_e / d delta [N/m], (k,)
    energy: NDArray[np.float64]  # its energy, unweighted [J], (k,)
