"""What the steps of a reproduction share: the run's meshes and load schedules, the context a
step reads and writes, the exception of a step that cannot run here, and the helpers that
describe an object and make the run's numbers JSON-safe."""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from softgrasp.model.objects import OBJECTS, make_object
from softgrasp.physics.body import build_body
from softgrasp.physics.fingertip.laws import HERTZ_PREFACTOR, contact_stiffness, effective_modulus


@dataclass(frozen=True)
class Settings:
    """Meshes and load schedules of one run (``quick`` or full)."""

    mesh_size_m: Mapping[str, float]
    compression_strain: float
    compression_steps: int
    indentation_depth_m: float

    @classmethod
    def of(cls, quick: bool) -> Settings:
        if quick:
            # Coarse: 4 BCC cells per cube edge (285 nodes), a ~210-node sphere.
            return cls({"cube": 0.0125, "sphere": 0.025}, 0.3, 10, 0.003)
        return cls({k: OBJECTS[k].mesh_size for k in ("cube", "sphere")}, 0.3, 30, 0.005)


class Skipped(Exception):
    """A step that cannot run here (not an error of the step)."""


@dataclass
class Context:
    out: Path
    settings: Settings
    plan_file: Path | None = None
    plan_status: str = "was not run"


Progress = Callable[[float], None]


def finite(x: Any) -> float | None:
    """``x`` as a float, or None when it is not finite."""
    x = float(x)
    return x if math.isfinite(x) else None


def jsonable(v: Any) -> Any:
    """``v`` with NumPy values, paths and non-finite floats made JSON-safe (NaN, inf -> None)."""
    if isinstance(v, dict):
        return {str(k): jsonable(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [jsonable(x) for x in v]
    if isinstance(v, np.ndarray):
        return jsonable(v.tolist())
    if isinstance(v, bool | np.bool_):
        return bool(v)
    if isinstance(v, int | np.integer):
        return int(v)
    if isinstance(v, float | np.floating):
        return finite(v)
    if isinstance(v, Path):
        return str(v)
    return v


def rel(a: float, b: float) -> float:
    """Relative difference of ``a`` from the reference ``b``."""
    return (a - b) / b


def linear_solver() -> str:
    """The linear solver the run's static and implicit solves use, for the report."""
    from softgrasp.linalg import pardiso

    return "MKL PARDISO" if pardiso.available() else "sparse LU / multigrid-preconditioned CG"


def mesh_info(body, mesh_size: float) -> dict[str, Any]:
    """The mesh and mass of ``body`` built at ``mesh_size`` [m], for the report."""
    return {
        "mesh_size_m": mesh_size,
        "nodes": body.mesh.n_nodes,
        "tets": body.mesh.n_tets,
        "facets": int(len(body.mesh.facets)),
        "extent_m": np.ptp(body.mesh.points, axis=0).tolist(),
        "mass_kg": body.total_mass,
    }


def object_of(name: str, settings: Settings):
    mesh, material, mass = make_object(name, settings.mesh_size_m[name])
    body = build_body(mesh, material, mass=mass)
    return body, {
        "name": name,
        "description": OBJECTS[name].description,
        **mesh_info(body, settings.mesh_size_m[name]),
        "material": body.material.describe(),
        "network": body.calibration.describe(),
    }


def power_fit(x: NDArray[np.float64], y: NDArray[np.float64]) -> float | None:
    """Exponent n of ``y ~ x^n``: the slope of a least-squares line in log-log (x, y > 0)."""
    sel = (x > 0) & (y > 0)
    if sel.sum() < 2:
        return None
    return float(np.polyfit(np.log(x[sel]), np.log(y[sel]), 1)[0])


def hertz_force(E: float, nu: float, R: float, delta: Any) -> Any:
    """Hertz: force [N] of a rigid sphere of radius ``R`` [m] pressed ``delta`` [m] into an elastic
    half-space of Young's modulus ``E`` [Pa] and Poisson's ratio ``nu``: the contact law
    K delta^(3/2) with Hertz's prefactor 4/3 and the effective modulus of a rigid indenter."""
    K = contact_stiffness(effective_modulus(math.inf, 0.0, E, nu), R, HERTZ_PREFACTOR)
    return K * np.asarray(delta) ** 1.5
