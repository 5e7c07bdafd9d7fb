"""Table 2, honestly: which parameters make the paper's forces and penetrations consistent.

The paper's thumb presses 20 mm into the rubber sphere with 2.2 N. For a rigid 8 mm fingertip on
the 64 mm sphere Hertz's law (contact radius a, ``F = 4/3 E* sqrt(R_eff) delta^1.5``,
``1 / R_eff = 1 / R + 1 / R_sphere``) makes that consistent only with ``E = 3 F (1 - nu^2) / (4
sqrt(R_eff) delta^1.5)``, an order of magnitude below Table 1's 79.3 kPa (:func:`implied_modulus`;
20 mm is beyond Hertz's small strains too). And the paper's 5.1 N in all is what three fingers
need at these contacts only with a friction coefficient near 0.13 (:func:`implied_friction`: the
rigid-body least normal forces, Eq. 21-22 with friction cones, that sum to it). The reproduction
plans the sphere again with those values beside the Table 1 run.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from softgrasp.errors import InfeasibleGrasp, NotConverged

__all__ = ["implied_modulus", "implied_friction", "consistent_runs"]


def implied_modulus(force_N: float, penetration_m: float, fingertip_R: float, object_R: float, nu: float) -> float:
    """The Young's modulus [Pa] for which Hertz's rigid sphere of radius ``fingertip_R`` on a
    sphere of radius ``object_R`` (Poisson's ratio ``nu``) needs ``force_N`` at ``penetration_m``."""
    r_eff = fingertip_R * object_R / (fingertip_R + object_R)
    e_star = 3.0 * force_N / (4.0 * math.sqrt(r_eff) * penetration_m**1.5)
    return e_star * (1.0 - nu * nu)


def implied_friction(
    points: NDArray[np.float64],
    push: NDArray[np.float64],
    com: NDArray[np.float64],
    mass: float,
    gravity: NDArray[np.float64],
    total_N: float,
) -> float:
    """The friction coefficient at which the least normal forces that hold a rigid object at these
    contacts (points (3, 3) [m], unit pushes into the object (3, 3)) sum to ``total_N`` [N]
    (bisection; the sum falls as mu rises)."""
    from softgrasp.grasp.equilibrium import minimum_normal_forces

    def need(mu: float) -> float:
        try:
            return float(minimum_normal_forces(points, push, mu, com, mass, gravity).sum())
        except InfeasibleGrasp:
            return math.inf

    lo, hi = 0.01, 2.0
    for _ in range(60):
        mid = math.sqrt(lo * hi)
        if need(mid) > total_N:
            lo = mid
        else:
            hi = mid
    return hi


def consistent_runs(body: Any, plan: Any, paper: dict[str, dict[str, float]], object_R: float) -> dict[str, Any]:
    """The implied E (per finger and their mean) and mu (at ``plan``'s contacts), and plans of the
    sphere with the mean E at the plan's mu and with both implied values (the softer sphere sags
    on the table: its grasp is searched again): set-points and penetrations, or why the plan
    failed."""
    from softgrasp.grasp.planner import plan_grasp
    from softgrasp.model.material import Material
    from softgrasp.physics.body import build_body

    cfg = plan.config
    m = body.material
    E = {
        n: implied_modulus(p["force_N"], p["penetration_m"], cfg.fingertip_radius, object_R, m.nu)
        for n, p in paper.items()
    }
    E_mean = float(np.mean(list(E.values())))
    push = plan.contact_points - plan.centres
    push /= np.linalg.norm(push, axis=1)[:, None]
    total = float(sum(p["force_N"] for p in paper.values()))
    mu = implied_friction(plan.contact_points, push, plan.com, body.total_mass, body.gravity, total)
    soft = build_body(body.mesh, Material(E_mean, m.nu, m.density, m.law, f"{m.name}, E from Table 2"), mass=body.total_mass)
    runs = []
    for label, mu_run in (("implied E, the plan's mu", cfg.contact.mu), ("implied E and mu", mu)):
        c = replace(cfg, contact=replace(cfg.contact, mu=mu_run))
        run: dict[str, Any] = {"label": label, "E_Pa": E_mean, "mu": mu_run}
        try:
            p = plan_grasp(soft, c)
            run["fingers"] = [
                {"name": f.name, "penetration_m": f.penetration, "force_N": f.force_norm} for f in p.fingers
            ]
        except (InfeasibleGrasp, NotConverged) as exc:
            run["failed"] = str(exc).split(";")[0]
        runs.append(run)
    return {"implied_E_Pa": E, "implied_E_mean_Pa": E_mean, "implied_mu": mu, "paper_total_force_N": total, "runs": runs}
