"""MJCF elements shared by softgrasp's MuJoCo scenes: number formatting, the ``<mujoco>`` root
with the solver options of :mod:`softgrasp.execution.mujoco.options`, the table, the contact
attributes of the geoms that touch the object, and the naming of fingertip geoms and servos."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from softgrasp.execution.mujoco.options import (
    CONTACT_SOLIMP,
    CONTACT_SOLREF,
    IMPRATIO,
    OBJECT_BIT,
    SOLVER,
    SOLVER_ITERATIONS,
    SOLVER_TOLERANCE,
    SPIN_ROLL,
    TABLE_BIT,
)
from softgrasp.physics.body import STANDARD_GRAVITY

__all__ = [
    "actuator_name",
    "add_table",
    "contact_attrs",
    "element",
    "fnum",
    "fvec",
    "mujoco_root",
    "quaternion",
    "tip_geom_name",
]


def fnum(v: float) -> str:
    """A number as MJCF text (12 significant digits)."""
    return f"{float(v):.12g}"


def fvec(values: ArrayLike) -> str:
    """Numbers as space-separated MJCF text."""
    return " ".join(fnum(v) for v in np.asarray(values, dtype=np.float64).ravel())


def quaternion(R: NDArray[np.float64]) -> NDArray[np.float64]:
    """Unit quaternion ``(w, x, y, z)`` of a rotation matrix (Shepperd's method)."""
    t = float(np.trace(R))
    if t > 0.0:
        s = 2.0 * math.sqrt(1.0 + t)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    qa = np.array(q)
    qa /= np.linalg.norm(qa)
    return qa if qa[0] >= 0.0 else -qa


def element(parent: ET.Element, tag: str, **attrs: Any) -> ET.Element:
    """Append a ``tag`` child to ``parent``; attributes given as None are left out."""
    return ET.SubElement(parent, tag, {k: str(v) for k, v in attrs.items() if v is not None})


def add_table(world: ET.Element, centre, reach: float, table_z: float, table_mu: float) -> None:
    """The table: a 20 mm box of half-width ``reach`` around ``centre`` with its top at ``table_z``."""
    thickness = 0.02
    element(
        world,
        "geom",
        name="table",
        type="box",
        size=fvec([reach, reach, 0.5 * thickness]),
        pos=fvec([centre[0], centre[1], table_z - 0.5 * thickness]),
        contype=str(TABLE_BIT),
        conaffinity=str(OBJECT_BIT),
        rgba="0.45 0.42 0.38 1",
        **contact_attrs(table_mu),
    )


def mujoco_root(model: str, timestep: float, impratio: float = IMPRATIO) -> ET.Element:
    """The ``<mujoco>`` element with softgrasp's compiler and solver options (discrete integrator,
    elliptic friction cones, their impedance ratio ``impratio``: :func:`~softgrasp.execution.mujoco
    .options.impratio` of the object where it is held)."""
    root = ET.Element("mujoco", model=model)
    element(root, "compiler", angle="radian", autolimits="true")
    element(
        root,
        "option",
        timestep=fnum(timestep),
        gravity=fvec([0.0, 0.0, -STANDARD_GRAVITY]),
        integrator="discrete",
        solver=SOLVER,
        cone="elliptic",
        impratio=fnum(impratio),
        iterations=str(SOLVER_ITERATIONS),
        tolerance=fnum(SOLVER_TOLERANCE),
    )
    return root


def contact_attrs(mu: float) -> dict[str, str]:
    """Attributes of a geom that touches the object: priority 1 (its friction ``mu`` and its
    solref/solimp win over the flex's), point contact with Coulomb friction (condim 3)."""
    return {
        "condim": "3",
        "priority": "1",
        "friction": fvec([mu, *SPIN_ROLL]),
        "solref": fvec(CONTACT_SOLREF),
        "solimp": fvec(CONTACT_SOLIMP),
    }


def tip_geom_name(tip_link: str) -> str:
    """Name of the sphere geom of the fingertip link ``tip_link``."""
    return f"{tip_link}_sphere"


def actuator_name(joint: str) -> str:
    """Name of the position servo of ``joint``."""
    return f"{joint}_servo"
