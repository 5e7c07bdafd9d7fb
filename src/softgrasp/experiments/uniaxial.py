"""The specimen's uniaxial law, its fit to a measured compression curve, and the edge law that
makes the simulated specimen follow it.

A compression test measures a *specimen*: nominal stress sigma = F / A against nominal strain
epsilon = travel / height (compressive positive). The calibration describes the material by that
uniaxial law,

    sigma(epsilon) = E (epsilon + c2 epsilon^2 + c3 epsilon^3),                 (specimen law)

E the small-strain Young's modulus, c2 > 0 and c3 > 0 stiffening in compression. The body's springs
act on *edge* strains, which differ from the specimen's axial strain (edges at an angle, lateral
expansion, the volume term), so the edge law is not the specimen law: :func:`edge_law_for` finds
the edge law (a :class:`~softgrasp.model.material.Tabulated` table on the compressive edge strains,
its tension side the odd mirror image) whose simulated lubricated specimen follows the specimen
law, by a fixed-point iteration on the simulated curve.

With platens that stick, the specimen is not in uniaxial stress: the measured force is the specimen
law times the platens' stiffening ratio R(epsilon) = F_friction / F_lubricated, both simulated with
the same body. Given R, the force is linear in (E, E c2, E c3): :func:`fit_linear` solves that
weighted linear least-squares problem exactly, with a covariance robust to the noise's form.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from softgrasp.errors import NotConverged
from softgrasp.experiments.compression import CompressionResult
from softgrasp.model.material import Tabulated

__all__ = [
    "LinearFit",
    "fit_linear",
    "fit_specimen_law",
    "specimen_columns",
    "specimen_stress",
    "EdgeLaw",
    "edge_law_for",
    "specimen_modulus",
]

#: Relative force below which a point's weight stops growing (a fraction of the largest force):
#: points at zero force carry no information on the law's shape and would get infinite weight.
WEIGHT_FLOOR = 0.01
#: Largest relative deviation of the simulated specimen's normalised curve from the specimen law
#: at which :func:`edge_law_for` stops.
EDGE_LAW_TOLERANCE = 1e-3


def specimen_stress(strain: NDArray[np.float64], c2: float, c3: float) -> NDArray[np.float64]:
    """The specimen law over E: epsilon + c2 epsilon^2 + c3 epsilon^3 (compressive positive)."""
    e = np.asarray(strain, dtype=np.float64)
    return e + c2 * e**2 + c3 * e**3


def specimen_columns(
    strain: NDArray[np.float64], scale: NDArray[np.float64], order: int
) -> NDArray[np.float64]:
    """Columns (P, order) of the force model F = sum_k p_k scale epsilon^k (k = 1..order):
    ``scale`` is the area times the platens' stiffening ratio at each point."""
    e = np.asarray(strain, dtype=np.float64)
    return np.stack([scale * e**k for k in range(1, order + 1)], axis=1)


@dataclass(frozen=True)
class LinearFit:
    """A weighted linear least-squares fit y ~ X p.

    Attributes
    ----------
    p: the coefficients, (K,).  cov: their covariance, (K, K).  model: X p, (P,).
    residual: y - X p, (P,).  weights: the weights of the last solve (1 / the model force).
    """

    p: NDArray[np.float64]
    cov: NDArray[np.float64]
    model: NDArray[np.float64]
    residual: NDArray[np.float64]
    weights: NDArray[np.float64]


def fit_linear(X: NDArray[np.float64], y: NDArray[np.float64], *, rounds: int = 4) -> LinearFit:
    """Fit ``y ~ X p`` by least squares on relative residuals (y - X p) / max(X p, floor), the
    weights taken from the previous round's model (iteratively reweighted; the first round uses
    the data), the floor ``WEIGHT_FLOOR`` times the largest force.

    The covariance is the heteroscedasticity-consistent (sandwich) estimate
    B (X_w^T diag(r_w^2) X_w) B n / (n - k), B = (X_w^T X_w)^-1: it assumes nothing about how the
    noise scales with the force (relative noise, a load cell's constant noise, or a mixture).
    """
    X = np.asarray(X, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    n, k = X.shape
    if n <= k:
        raise NotConverged(f"{n} data points cannot determine {k} coefficients")
    floor = WEIGHT_FLOOR * float(np.abs(y).max())
    ref = np.abs(y)
    for _ in range(max(rounds, 1)):
        w = 1.0 / np.maximum(ref, floor)
        p, *_ = np.linalg.lstsq(X * w[:, None], y * w, rcond=None)
        ref = np.abs(X @ p)
    Xw = X * w[:, None]
    rw = (y - X @ p) * w
    B = np.linalg.pinv(Xw.T @ Xw)
    meat = (Xw * (rw**2)[:, None]).T @ Xw
    cov = B @ meat @ B * n / (n - k)
    return LinearFit(p, cov, X @ p, y - X @ p, w)


def fit_specimen_law(
    strain: NDArray[np.float64], force: NDArray[np.float64], scale: NDArray[np.float64] | float
) -> tuple[list[float], NDArray[np.float64]]:
    """Fit F = scale E (epsilon + c2 epsilon^2 + c3 epsilon^3) (``scale``: the area times the
    platens' stiffening ratio, per point or one number) by :func:`fit_linear` on the coefficients
    p = (E, E c2, E c3). Returns ([E, c2, c3], their covariance (3, 3)), the latter to first order
    from p's."""
    e = np.asarray(strain, dtype=np.float64)
    lf = fit_linear(specimen_columns(e, np.broadcast_to(scale, e.shape), 3), force)
    p = lf.p
    E = float(p[0])
    G = np.array([[1.0, 0.0, 0.0], [-p[1] / E**2, 1.0 / E, 0.0], [-p[2] / E**2, 0.0, 1.0 / E]])
    return [E, float(p[1]) / E, float(p[2]) / E], G @ lf.cov @ G.T


def _slope(strain: NDArray[np.float64], stress: NDArray[np.float64], upto: float) -> float:
    """Least-squares slope through the origin over strains up to ``upto`` (at least two points):
    how the compression test measures its apparent modulus."""
    sel = (strain > 0) & (strain <= upto * (1 + 1e-9))
    if sel.sum() < 2:
        sel = np.zeros_like(strain, dtype=bool)
        sel[np.flatnonzero(strain > 0)[:2]] = True
    return float(strain[sel] @ stress[sel] / (strain[sel] @ strain[sel]))


def specimen_modulus(res: CompressionResult, c2: float, c3: float) -> float:
    """E of the specimen law (c2, c3) whose initial slope matches the simulated test ``res``
    (slopes through the origin up to ``res.fit_strain``): the body's own specimen modulus, which
    differs from its Material's E by the spring network's small-strain error."""
    eps = res.strain[1:]
    return _slope(res.strain, res.stress_Pa, res.fit_strain) / _slope(
        eps, specimen_stress(eps, c2, c3), res.fit_strain
    )


@dataclass(frozen=True)
class EdgeLaw:
    """An edge law found by :func:`edge_law_for`.

    Attributes
    ----------
    law: the table (normalised by its initial slope when used by a Material).
    lubricated: the simulated lubricated test of the body with it.
    deviation: largest relative deviation of the simulated normalised curve from the specimen law.
    simulations: simulated tests used.
    nodes, values: compressive edge strains and normalised edge stresses of the table (positive).
    """

    law: Tabulated
    lubricated: CompressionResult
    deviation: float
    simulations: int
    nodes: NDArray[np.float64]
    values: NDArray[np.float64]


def _table(nodes: NDArray[np.float64], values: NDArray[np.float64], c2: float, c3: float) -> Tabulated:
    """The edge law of compressive strains ``nodes`` and normalised stresses ``values``.

    Its initial slope is pinned to 1 (a node at a twentieth of the first strain on the line
    s = epsilon), so the law shapes the curve only. Beyond the last node it follows the specimen
    law's shape times the last node's ratio to it, to 1.5 times the last strain (edges stretched
    a little beyond the axial strain stay on the law), then the end slope. Its tension side is the
    odd mirror image (a compression test measures no tension).
    """
    e0 = nodes[0] / 20.0
    top = nodes[-1] * np.array([1.25, 1.5])
    ext = values[-1] * specimen_stress(top, c2, c3) / float(specimen_stress(nodes[-1:], c2, c3)[0])
    if not (np.diff(ext) > 0).all() or ext[0] <= values[-1]:
        # the end slope, kept positive (a law whose stress stops growing is not a stable one)
        slope = max((values[-1] - values[-2]) / (nodes[-1] - nodes[-2]), 1e-3 * values[-1] / nodes[-1])
        ext = values[-1] + slope * (top - nodes[-1])
    e = np.concatenate([[e0], nodes, top])
    v = np.concatenate([[e0], values, ext])
    return Tabulated(-e, -v)


def edge_law_for(
    simulate: Callable[[Tabulated], CompressionResult],
    c2: float,
    c3: float,
    strain: float,
    *,
    start: EdgeLaw | None = None,
    max_iterations: int = 12,
    tolerance: float = EDGE_LAW_TOLERANCE,
) -> EdgeLaw:
    """The edge law whose lubricated specimen follows the specimen law (c2, c3) in shape up to
    the nominal strain ``strain``.

    ``simulate(law)`` runs the lubricated compression test of the body with that edge law (its
    strain levels must not depend on the law, and should reach beyond ``strain``: the last
    increments of a test are the least accurate). Starting from the specimen law itself (or from
    ``start``), each round multiplies the table's stress at edge strain epsilon by the ratio of the
    specimen law to the simulated specimen's stress at axial strain epsilon, both normalised by
    their initial slopes (the body's small-strain modulus is the spring network's: the law shapes
    the curve only), until the largest relative deviation up to ``strain`` is below ``tolerance``;
    table nodes beyond ``strain`` take the ratio of the last one within it.
    """
    nodes = None if start is None else start.nodes
    values = None if start is None else start.values
    count = 0
    best: EdgeLaw | None = None
    for _ in range(max_iterations):
        if nodes is None or values is None:
            first = np.array([0.01, 0.02]) * strain
            law = _table(first, specimen_stress(first, c2, c3), c2, c3)
        else:
            law = _table(nodes, values, c2, c3)
        res = simulate(law)
        count += 1
        eps = res.strain[1:]
        target = specimen_stress(eps, c2, c3)
        if nodes is None or values is None or nodes.shape != eps.shape or not np.allclose(nodes, eps):
            # the first run only fixes the strain levels: restart from the specimen law on them
            nodes = eps.copy()
            values = np.maximum.accumulate(target) + 1e-12 * np.arange(len(target))
            continue
        inside = eps <= strain * (1 + 1e-9)
        got = res.stress_Pa[1:] / _slope(res.strain, res.stress_Pa, res.fit_strain)
        want = target / _slope(eps, target, res.fit_strain)
        ratio = want / got
        deviation = float(np.abs(1.0 / ratio[inside] - 1.0).max())
        if best is None or deviation < best.deviation:
            best = EdgeLaw(law, res, deviation, count, nodes.copy(), values.copy())
        if deviation < tolerance:
            break
        ratio[~inside] = ratio[inside][-1]
        values = values * ratio
        # keep the table strictly increasing (the law's stress must grow with strain)
        values = np.maximum.accumulate(values) + 1e-12 * np.arange(len(values))
    if best is None:
        raise NotConverged("the edge law of the specimen law could not be simulated")
    return EdgeLaw(best.law, best.lubricated, best.deviation, count, best.nodes, best.values)
