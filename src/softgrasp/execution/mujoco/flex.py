"""The soft object in MuJoCo: a 3-D flex built from softgrasp's tetrahedral mesh.

:func:`add_object` appends a ``flexcomp`` of type ``direct``, ``dim=3``, radius 0, built from
``points`` and ``tets``. flexcomp gives every point a body with three world-axis slide joints and
the mass ``mass / N`` (uniform, unlike softgrasp's volume-lumped node masses; the sum is ``mass``)
and keeps the order of ``points`` for the flex vertices. Elasticity is MuJoCo's continuum model
(Saint Venant-Kirchhoff on linear tets, Lame constants from ``young`` and ``poisson``) with a
Rayleigh damping time ``damping``; no edge constraints; self-collision off. The flex has contact
priority 0, so the table's and the fingertips' friction and softness apply to its contacts.

Validation (MuJoCo 4.0.0, softgrasp's rubber sphere: R = 64 mm, 50 g, E = 79.3 kPa, nu = 0.45;
``tests/test_mujoco_scene.py``)
-----------------------------------------------------------------------------------------------
* Affine patch test: the flex's elastic energy for uniaxial, volumetric and shear strains equals
  ``V (mu tr(e^2) + lambda/2 tr(e)^2)`` to 1.5e-4: ``young`` and ``poisson`` mean what they say.
* Resting, 388 nodes: after 1 s the table carries ``m g`` to 2e-4, the centre of mass sags
  0.16 mm and rocks by ~0.2-0.5 mm on its support tripod, no warning. The 2196-node sphere
  (``make_object("sphere", 0.008)``) also carries ``m g`` (1.5e-3) but is only neutrally stable:
  its elastic sag (0.37 mm) exceeds the relief of its small support facets, and it rolls ~9 mm
  in the first second (independent of damping, step size and node masses).
* Fingertip (first finger pointing down) pressed into the top node: the force grows
  monotonically, nearly linearly (0.52 / 1.03 / 2.01 / 2.94 N at 0.5 / 1 / 2 / 3 mm). Hertz for a
  rigid 8 mm fingertip (``E* = E / (1 - nu^2)``, ``R_eff = (1/0.064 + 1/0.008)^-1``) gives
  1.84 N at 3 mm: ratio 1.60 on the 388-node mesh (about 2.0 pressing on a face), 1.09 (1.07)
  on 2196 nodes. The coarse mesh is stiffer than the continuum: its 16 mm elements are larger than
  the Hertz contact radius (4.6 mm at 3 mm), so the load acts like a punch of element size on
  linear tets that stiffen (lock) at nu = 0.45; refining converges to Hertz.
* Cost: the simulation time grows with the flex size (the ``qacc_smooth`` PCG and the constraint
  solve dominate; the hand costs nothing noticeable): a 2196-node sphere costs about ten times
  as much per step as the 388-node one.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET

from softgrasp.execution.mujoco.elements import element, fnum, fvec
from softgrasp.execution.mujoco.options import (
    CONTACT_SOLIMP,
    CONTACT_SOLREF,
    OBJECT_BIT,
    OBJECT_NAME,
    SPIN_ROLL,
    TABLE_BIT,
    TIP_BIT,
)
from softgrasp.execution.mujoco.spec import SceneSpec

__all__ = ["add_object"]


def add_object(world: ET.Element, spec: SceneSpec) -> None:
    """Append the object of ``spec`` to ``world`` as the flex :data:`OBJECT_NAME`."""
    flex = element(
        world,
        "flexcomp",
        name=OBJECT_NAME,
        type="direct",
        dim="3",
        point=fvec(spec.points),
        element=" ".join(str(int(i)) for i in spec.tets.ravel()),
        mass=fnum(spec.mass),
        radius="0",
        rgba="0.85 0.3 0.25 1",
    )
    # the table and the fingertips have priority 1: their friction and solver parameters win
    element(
        flex,
        "contact",
        selfcollide="none",
        contype=str(OBJECT_BIT),
        conaffinity=str(TABLE_BIT | TIP_BIT),
        condim="3",
        priority="0",
        friction=fvec([min(spec.mu, spec.table_mu), *SPIN_ROLL]),
        solref=fvec(CONTACT_SOLREF),
        solimp=fvec(CONTACT_SOLIMP),
    )
    element(flex, "edge", equality="false")
    element(
        flex, "elasticity", young=fnum(spec.young), poisson=fnum(spec.poisson), damping=fnum(spec.damping)
    )
