"""Objects, materials and hands of the public API: what a grasp is planned for and with.

:func:`load_object` gives a :class:`SoftObject` (the mass-spring body of a built-in object, a
parametric shape or a mesh file, with its material); :func:`material` a preset
:class:`~softgrasp.model.material.Material`; :func:`load_hand` a hand model.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from softgrasp.errors import ConfigError
from softgrasp.io.materialfile import MaterialFile, is_material_file, read_material_file
from softgrasp.model.material import Material
from softgrasp.model.ranges import UNITS

if TYPE_CHECKING:
    from softgrasp.hand.kinematics import HandModel
    from softgrasp.model.mesh.generate import LocalRefinement
    from softgrasp.model.mesh.tetmesh import TetMesh
    from softgrasp.physics.body import Body

__all__ = ["UNITS", "SoftObject", "load_object", "refined", "material", "load_hand"]


@dataclass(frozen=True, eq=False)
class SoftObject:
    """A soft object ready to be planned for, compressed, indented or calibrated.

    Attributes
    ----------
    source: the built-in object (``sphere``, ``cube``), shape (``box:WxDxH``, ``cylinder:DxH``,
        ``ball:R``; metres) or mesh file it was made from.
    body: its mass-spring model (mesh resting on the table, material, masses, springs).
    material_spec: the material as given (preset name, ``key=value`` list, material file,
        :class:`Material`), or None for the object's own.
    material_file: the material file read from ``material_spec`` (its ``[contact]`` table sets the
        fingertip friction of plans and indentations), or None.
    mesh_size_m: the element size asked for [m], or None for the object's default.
    units: the length unit of a mesh file (``m``, ``cm``, ``mm``).
    reorient: whether inverted tets of a mesh file were flipped.
    density_kg_m3, given_mass_kg: the density [kg/m^3] or total mass [kg] given over the
        material's, or None.
    transform: the transform (4, 4) from the source's coordinates to the body's mesh,
        ``p_body = T p_source`` (homogeneous; a mesh file's coordinates in ``units``, metres out):
        the scaling by the units, then the turn and move that rest the object on the table.
    refinement: the finer elements asked for near points of the source
        (:class:`~softgrasp.model.mesh.generate.LocalRefinement`), or None.
    """

    source: str
    body: Body
    material_spec: str | Material | None = None
    material_file: MaterialFile | None = None
    mesh_size_m: float | None = None
    units: str = "m"
    reorient: bool = False
    density_kg_m3: float | None = None
    given_mass_kg: float | None = None
    transform: NDArray[np.float64] = field(default_factory=lambda: np.eye(4))
    refinement: LocalRefinement | None = None

    @property
    def name(self) -> str:
        """The object's label in plan outputs: a mesh file's stem, else the source (a built-in
        object or a shape, whose sizes may have decimal points)."""
        from softgrasp.model.objects import is_mesh_file

        return Path(self.source).stem if is_mesh_file(self.source) else self.source

    @property
    def mesh(self) -> TetMesh:
        """The tetrahedral mesh, resting on the table plane z = 0 [m]."""
        return self.body.mesh

    @property
    def material(self) -> Material:
        """The object's material."""
        return self.body.material

    @property
    def mass_kg(self) -> float:
        """Total mass [kg]."""
        return float(self.body.total_mass)

    @property
    def density_given(self) -> bool:
        """Whether the material as given carries its own density (a calibration then writes it)."""
        spec, mf = self.material_spec, self.material_file
        if self.density_kg_m3 is not None or self.given_mass_kg is not None:
            return True
        if mf is not None:
            return mf.material is not None and mf.material.density is not None
        if isinstance(spec, Material):
            return spec.density is not None
        return spec is not None and "density" in spec

    def summary(self) -> str:
        """One line for people: the mesh and the mass."""
        return f"{self.body.mesh.summary()}, mass {self.mass_kg * 1e3:.1f} g"

    def to_dict(self, folder: str | Path | None = None) -> dict[str, object]:
        """JSON-ready description: name, mesh and model sizes, material, the local refinement
        asked for (units in the keys). With
        ``folder`` (the output folder that records it), a mesh file is named by its path relative
        to it (:func:`~softgrasp.io.portable.portable_path`), not by this machine's path."""
        from softgrasp.io.portable import portable_path

        name = self.source if folder is None else portable_path(self.source, folder)
        out = {"name": name, **self.body.describe()}
        if self.refinement is not None:
            r = self.refinement
            out["refinement"] = {
                "points_m": [list(p) for p in r.points_m],
                "size_m": r.size_m,
                "radius_m": r.radius_m,
            }
        return out


def _material_file(
    spec: str | Material | MaterialFile | None,
) -> tuple[str | Material | None, MaterialFile | None]:
    if isinstance(spec, MaterialFile):
        return str(spec.path), spec
    if isinstance(spec, str) and is_material_file(spec):
        return spec, read_material_file(spec)
    return spec, None


def load_object(
    source: str | Path = "sphere",
    *,
    units: str = "m",
    material: str | Material | MaterialFile | None = None,
    mesh_size_m: float | None = None,
    reorient: bool = False,
    density_kg_m3: float | None = None,
    mass_kg: float | None = None,
    volume_term: str = "element",
    refinement: LocalRefinement | None = None,
) -> SoftObject:
    """The soft object ``source``: a built-in object (``sphere``: the paper's 64 mm rubber sphere,
    ``cube``: its 50 mm foam cube), a shape (``box:0.04x0.03x0.02``, ``cylinder:DxH``, ``ball:R``,
    metres) or a mesh file (a tet mesh meshio reads, or a closed ``.stl``/``.obj``/``.ply``/``.off``
    surface, tet-meshed by gmsh).

    Parameters
    ----------
    units:
        Length unit of a mesh file's coordinates: ``m``, ``cm`` or ``mm``.
    material:
        A :class:`Material`, a preset name (``rubber``, ``foam``), a ``key=value`` list
        (``E=80e3,nu=0.45,density=950``) or a material file (``.toml``, as ``softgrasp calibrate``
        writes, optionally followed by overrides: ``material.toml,density=1000``); default the
        object's own. A material with a density decides the mass; one without keeps a built-in
        object's mass. A mesh file or a shape given without a material takes the ``rubber``
        preset's E and nu and, without a density or mass, 1000 kg/m^3 (water's), each with a
        :class:`~softgrasp.errors.SoftgraspWarning` (a shape given its density or mass: none).
    density_kg_m3, mass_kg:
        The object's density [kg/m^3] or its total mass [kg] (one of them), over the material's.
    mesh_size_m:
        Target element size [m]; default the object's (a file: one eighth of its bounding box's
        mean side).
    reorient:
        Flip inverted tets of a volume mesh file instead of refusing it.
    volume_term:
        The body's volume term: ``element`` (per tet) or ``nodal`` (per node; no volumetric
        locking as nu nears 1/2, at about four times the Newton matrix's blocks:
        :mod:`softgrasp.physics.nodal_volume`).
    refinement:
        Finer elements near points of a built-in object or a shape (a box is then meshed by gmsh
        instead of on its grid), in the coordinates softgrasp generates it in (standing on
        z = 0, its centroid on the z axis: the sphere's top at (0, 0, 0.128)):
        :class:`~softgrasp.model.mesh.generate.LocalRefinement`.
    """
    from softgrasp.io.options import load_placed_body
    from softgrasp.model.ranges import check, check_volume_term

    if units not in UNITS:
        raise ConfigError(f"units must be one of {', '.join(UNITS)}, got {units!r}")
    check_volume_term(volume_term)
    if isinstance(material, dict):
        raise ConfigError("material must be a Material, a preset name, key=value text or a .toml file")
    if density_kg_m3 is not None and mass_kg is not None:
        raise ConfigError("give the object's density_kg_m3 or its mass_kg, not both")
    overrides = {}
    if density_kg_m3 is not None:
        overrides["density"] = check("density", density_kg_m3, "density_kg_m3")
    if mass_kg is not None:
        overrides["mass"] = check("mass", mass_kg, "mass_kg")
    source = str(source)
    spec, mfile = _material_file(material)
    body, T = load_placed_body(
        source, mesh_size_m, spec, reorient=reorient, mfile=mfile, overrides=overrides, scale=UNITS[units],
        volume=volume_term, refinement=refinement,
    )  # fmt: skip
    T.setflags(write=False)
    return SoftObject(
        source, body, spec, mfile, mesh_size_m, units, reorient, density_kg_m3, mass_kg, T, refinement
    )


def refined(obj: SoftObject, refinement: LocalRefinement) -> SoftObject:
    """``obj`` meshed again with ``refinement`` (points in the coordinates softgrasp generates it
    in, :func:`load_object`); the same source, mesh size, material, mass and volume term. The
    new mesh rests on the table in its own stable pose (a box is meshed by gmsh instead of on its
    grid). MeshError for a mesh file (it is not meshed here). The defaults ``obj`` took were said
    when it was loaded (:class:`~softgrasp.errors.SoftgraspWarning`): the remake does not say them
    again."""
    import warnings

    from softgrasp.errors import SoftgraspWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SoftgraspWarning)
        return load_object(
            obj.source,
            units=obj.units,
            material=obj.material_spec,
            mesh_size_m=obj.mesh_size_m,
            reorient=obj.reorient,
            density_kg_m3=obj.density_kg_m3,
            mass_kg=obj.given_mass_kg,
            volume_term=obj.body.volume,
            refinement=refinement,
        )


def material(name: str) -> Material:
    """The preset material ``name`` (``rubber``, ``foam``: Table 1 of the reference paper), or a
    ``key=value`` list (``E=80e3,nu=0.45,density=950``, optionally after a preset name)."""
    from softgrasp.model.material import PRESETS, parse_material

    if name in PRESETS:
        return PRESETS[name]
    mat, mass = parse_material(name)
    if mass is not None:
        raise ConfigError("a material has no mass; give density=... (kg/m^3) instead of mass=...")
    return mat


def load_hand(
    name: str | Path = "shadow_like",
    fingertips: Mapping[str, str] | str | None = None,
    fingertip_radius_m: float | None = None,
) -> HandModel | None:
    """The hand: ``shadow_like`` (the packaged Shadow-like hand), ``parallel_jaw`` (the packaged
    two-finger gripper, 0-85 mm), a URDF or MJCF file, or ``none`` (free fingertips: returns None).

    ``fingertips`` maps the planner's fingers to the file's fingertip links (MJCF: bodies),
    ``{"thumb": "th_tip", "first": "ff_tip", "middle": "mf_tip"}`` (or ``left``/``right`` for a
    gripper), also as text ``thumb=th_tip,first=ff_tip,middle=mf_tip``; default: links named
    ``th_tip``, ``ff_tip``, ``mf_tip``. The fingertip radius is the link's collision sphere's;
    ``fingertip_radius_m`` overrides it (and is needed when the link has no sphere)."""
    from softgrasp.io.options import hand_model

    return hand_model(str(name), fingertips, fingertip_radius_m)
