"""Fingertips and contact parameters.

Defaults for what the paper does not give (DESIGN.md §4), each with its source:

* ``mu = 0.8`` — silicone elastomer fingertip skin on rubber or polyurethane foam: dry
  rubber-on-rubber friction is typically 0.6-1.0.
* ``exponent = 1.5`` — Hertz's exponent, the only one for which K's units (Eq. 11) work.
* ``law = "resolved"`` — the object's compliance counted once: Hertz's law for a sphere less the
  part of the object's compliance its mesh resolves (:mod:`softgrasp.physics.fingertip.resolved`);
  ``"paper"`` is the paper's K delta^n in series with the meshed body (Eq. 9-11), for reproducing it.
* ``prefactor`` — Hertz's 4/3 under the resolved law; the paper's K = 2 Psi sqrt(R) (Eq. 11) under
  its own.
* ``normals = "smooth"`` under the resolved law — a contact pushes along the object's smooth
  surface's normal at the contact point (:mod:`softgrasp.model.mesh.normals`), not along its
  facet's, tilted by up to half the angle between neighbouring facets; ``"facet"`` (the paper's)
  under its own law.
* ``gamma = 10 N s/m^2`` — C = 4 pi R gamma is then 1.0 N s/m for an 8 mm fingertip: 5 mN of
  damping force at the paper's 5 mm/s closing speed, small next to the elastic force, enough to damp
  contact chatter in explicit runs.
* tangential stiffness ``k_t = r (dF_n/d delta)`` with Mindlin's ratio r = 2(1 - nu)/(2 - nu) of the
  object's nu, at the contact's penetration (not below ``min_depth_ratio * R``); ``c_t = r C``.
* fingertip ``E = inf`` — effectively rigid (a steel- or PLA-cored fingertip is 10^4 - 10^6 times
  stiffer than the paper's objects); give E and nu for a soft fingertip (Eq. 12).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from softgrasp.errors import ContactError
from softgrasp.model.ranges import RANGES
from softgrasp.physics.fingertip.laws import HERTZ_PREFACTOR, PAPER_PREFACTOR, RESOLUTION

__all__ = ["Fingertip", "ContactParams"]


@dataclass(frozen=True)
class Fingertip:
    """A spherical fingertip (the paper's hemisphere is its working half) moving at constant
    velocity: centre(t) = centre + velocity t.

    Attributes
    ----------
    radius: R [m], > 0.
    centre: centre at t = 0 [m], (3,).
    velocity: linear velocity of the centre [m/s], (3,).
    omega: angular velocity [rad/s], (3,) (Eq. 1-2).
    E: Young's modulus of the fingertip [Pa]; ``inf`` = rigid.
    nu: Poisson ratio of the fingertip.
    name: label (``thumb``, ``first``, ``middle`` ...).
    """

    radius: float
    centre: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    velocity: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    omega: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    E: float = math.inf
    nu: float = 0.3
    name: str = "finger"

    def __post_init__(self) -> None:
        if not (math.isfinite(self.radius) and self.radius > 0):
            raise ContactError(
                f"fingertip {self.name!r}: radius = {self.radius} m is invalid; it must be > 0"
            )
        for k in ("centre", "velocity", "omega"):
            a = np.asarray(getattr(self, k), dtype=np.float64)
            if a.shape != (3,) or not np.isfinite(a).all():
                raise ContactError(f"fingertip {self.name!r}: {k} must be 3 finite numbers, got {a.tolist()}")
            object.__setattr__(self, k, a)
        if not (self.E > 0 and -1.0 < self.nu < 0.5):
            raise ContactError(f"fingertip {self.name!r}: E = {self.E} Pa, nu = {self.nu} out of range")

    def centre_at(self, t: float) -> NDArray[np.float64]:
        """Centre [m] at time t."""
        return self.centre + t * self.velocity

    def describe(self) -> dict[str, object]:
        return {
            "name": self.name,
            "radius_m": self.radius,
            "centre_m": self.centre.tolist(),
            "velocity_m_s": self.velocity.tolist(),
            "omega_rad_s": self.omega.tolist(),
            "E_Pa": None if math.isinf(self.E) else self.E,
            "nu": self.nu,
        }


@dataclass(frozen=True)
class ContactParams:
    """Parameters of the fingertip contact model (see the module docstring for the defaults).

    Attributes
    ----------
    mu: Coulomb friction coefficient.
    exponent: n of K delta^n (Eq. 9); 1.5 under the resolved law.
    prefactor: c of K = c Psi sqrt(R) (Eq. 11); default (None) the law's: 4/3 (Hertz) for the
        resolved law, 2 for the paper's.
    gamma: gamma of C = 4 pi R gamma (Eq. 13) [N s/m^2].
    damping: ``"linear"`` (paper: K delta^n + C delta_dot) or ``"hunt-crossley"``
        (K delta^n + C delta^n delta_dot, with C then read as lambda).
    rule: ``"patch"`` (default): a fingertip's elastic normal force is F(delta_max), with
        delta_max = R - dist(centre, surface) its overlap with the surface, shared among every
        facet the sphere overlaps by weights w_j proportional to A_j cos_j delta_j (delta_j =
        R - |c - Q_j|, Q_j the facet's point closest to the centre, cos_j the cosine between the
        facet's normal and c - Q_j: its area seen from the centre), each part along its facet's
        normal and applied at Q_j. Exactly K delta^n along the normal on a flat surface for any
        mesh; the load spreads over the whole contact patch however fine the mesh; continuous as
        facets enter or leave the patch (at zero overlap) or turn edge-on to the centre; at a
        right-angled convex edge the parts add up to a push along c - Q.
        ``"facet"``: the paper's literal rule, Sec. 3.1: a facet touches when the
        centre's projection lies inside it, and each touched facet gets the full K delta_j^n (the
        total grows with the number of facets touched).
    tangential_ratio: k_t / k_n; ``None`` for Mindlin's 2(1 - nu)/(2 - nu) of the object.
    min_depth_ratio: k_t is evaluated at a penetration of at least this fraction of R.
    law: ``"resolved"`` (default): the fingertip's elastic normal force is Hertz's less the share
        of the object's compliance that its mesh resolves, so the compliance is counted once
        (:mod:`softgrasp.physics.fingertip.resolved`); ``"paper"``: K delta^n (Eq. 9-11).
    resolution: the mesh's resolution length at a contact over the patch's facet size (resolved
        law; :data:`softgrasp.physics.fingertip.laws.RESOLUTION`).
    normals: ``"smooth"``: each pair's normal is the object's smooth surface's at its contact
        point, interpolated from the mesh's corner normals (Phong's normal; edges sharper than
        :data:`softgrasp.model.mesh.normals.CREASE_DEG` kept); ``"facet"``: its facet's (the
        paper's). Default (None) the law's: smooth for the resolved law, facet for the paper's.
    """

    mu: float = 0.8
    exponent: float = 1.5
    prefactor: float | None = None
    gamma: float = 10.0
    damping: str = "linear"
    rule: str = "patch"
    tangential_ratio: float | None = None
    min_depth_ratio: float = 0.01
    law: str = "resolved"
    resolution: float = RESOLUTION
    normals: str | None = None

    def __post_init__(self) -> None:
        if self.law not in ("resolved", "paper"):
            raise ContactError(f"contact law must be 'resolved' or 'paper', got {self.law!r}")
        if self.normals is None:
            object.__setattr__(self, "normals", "smooth" if self.law == "resolved" else "facet")
        if self.normals not in ("smooth", "facet"):
            raise ContactError(f"contact normals must be 'smooth' or 'facet', got {self.normals!r}")
        if self.prefactor is None:
            object.__setattr__(self, "prefactor", HERTZ_PREFACTOR if self.law == "resolved" else PAPER_PREFACTOR)
        checks = {
            "mu": RANGES["mu"].contains(self.mu),
            "exponent": self.exponent >= 1.0,
            "prefactor": self.prefactor > 0,
            "gamma": self.gamma >= 0,
            "min_depth_ratio": 0 < self.min_depth_ratio < 1,
            "resolution": self.resolution >= 0,
        }
        for k, ok in checks.items():
            v = getattr(self, k)
            if not (ok and math.isfinite(v)):
                hint = f": it must lie in {RANGES['mu'].text}" if k == "mu" else ""
                raise ContactError(f"contact parameter {k} = {v} is invalid{hint}")
        if self.damping not in ("linear", "hunt-crossley"):
            raise ContactError(f"damping must be 'linear' or 'hunt-crossley', got {self.damping!r}")
        if self.rule not in ("patch", "facet"):
            raise ContactError(f"rule must be 'patch' or 'facet', got {self.rule!r}")
        if self.tangential_ratio is not None and not self.tangential_ratio > 0:
            raise ContactError(f"tangential_ratio = {self.tangential_ratio} must be > 0")
        if self.law == "resolved" and self.exponent != 1.5:
            raise ContactError(
                f"the resolved contact law is Hertz's (exponent 1.5), got exponent = {self.exponent}; "
                "use the paper's law (law='paper', --contact-law paper) for another exponent"
            )

    def updated(self, **changes: object) -> ContactParams:
        """These parameters with ``changes``; a change of ``law`` also brings that law's defaults
        (stiffness prefactor and normals) where ``changes`` does not give them, not this law's."""
        if changes.get("law", self.law) != self.law:
            changes = {"prefactor": None, "normals": None, **changes}
        return replace(self, **changes)  # type: ignore[arg-type]

    def describe(self) -> dict[str, object]:
        return {
            "mu": self.mu,
            "exponent": self.exponent,
            "stiffness_prefactor": self.prefactor,
            "gamma_N_s_m2": self.gamma,
            "damping": self.damping,
            "rule": self.rule,
            "tangential_ratio": self.tangential_ratio,
            "min_depth_ratio": self.min_depth_ratio,
            "law": self.law,
            "resolution": self.resolution,
            "normals": self.normals,
        }
