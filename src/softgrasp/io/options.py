"""From plan options (what ``softgrasp plan`` and a sweep case name) to the object and the planner
configuration: one mapping shared by the command line, ``--config`` files and sweeps.

Options are plain values: ``object`` (built-in name, shape or mesh file), ``mesh_size`` [m],
``units`` (the length unit of a mesh file's coordinates or a shape's sizes: ``m``, ``cm``, ``mm``),
``material`` (preset, ``key=value`` list or a ``.toml`` material file), ``density`` [kg/m^3] or
``mass`` [kg] of the object (over its material's), the planner's settings
(:data:`PLAN_DEFAULTS`; ``grasp`` names a ``plan.json`` whose initial grasp is closed from instead
of searching for one), and optional material overrides (:data:`MATERIAL_OVERRIDES`: ``E`` [Pa],
``nu``, ``density`` [kg/m^3], ``mass`` [kg], ``a2``, ``a3``) applied over the object's material;
``volume_term`` (``element`` or ``nodal``: :attr:`~softgrasp.physics.body.Body.volume`).
"""

from __future__ import annotations

import numbers
from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from softgrasp.errors import ConfigError, MaterialError
from softgrasp.io.materialfile import MaterialFile, is_material_file, read_material_file
from softgrasp.model.material import Material
from softgrasp.model.ranges import RANGES, check_units

if TYPE_CHECKING:  # the heavy modules load when used: the command line's --help stays quick
    from softgrasp.grasp.planner import PlanConfig
    from softgrasp.model.mesh.generate import LocalRefinement
    from softgrasp.physics.body import Body
    from softgrasp.physics.fingertip.params import ContactParams

__all__ = [
    "PLAN_DEFAULTS",
    "MATERIAL_OVERRIDES",
    "TEXT_OPTIONS",
    "check_option",
    "check_inputs",
    "scheduler_address",
    "load_body",
    "load_placed_body",
    "hand_model",
    "contact_params",
    "plan_config",
    "material_file",
]

#: ``softgrasp plan`` options that a --config TOML file (or a sweep) may set, with their defaults.
PLAN_DEFAULTS: dict[str, object] = {
    "object": "sphere",
    "material": None,
    "mesh_size": None,
    "units": "m",
    "mu": 0.8,
    "fingertip_radius": None,
    "step": 0.0005,
    "solver": "quasistatic",
    "safety_factor": 1.25,
    "hold_time": 1.0,
    "max_squeeze": 0.5,
    "refine": 12,
    "hand": "shadow_like",
    "fingertips": None,
    "min_spread": None,
    "max_spread": None,
    "max_aperture": None,
    "grasp": None,
    "contact_law": "resolved",
    "max_pressure": None,
    "max_strain": None,
    "out": "softgrasp-out/plan",
    "reorient": False,
    "density": None,
    "mass": None,
    "volume_term": "element",
}

#: Material parameters a sweep may set over the object's material.
MATERIAL_OVERRIDES = ("E", "nu", "density", "mass", "a2", "a3")

#: Plan options whose values are text, and what each names (the others are numbers, but
#: ``reorient``, a boolean).
TEXT_OPTIONS: dict[str, str] = {
    "object": "a built-in object, a shape such as box:0.04x0.03x0.02, or a mesh file",
    "material": "a preset (foam, rubber), E=..,nu=..,density=.. or a .toml material file",
    "units": "m, cm or mm",
    "solver": "quasistatic or dynamic",
    "hand": "shadow_like, parallel_jaw, none, a URDF or an MJCF file",
    "fingertips": "FINGER=LINK pairs, e.g. thumb=th_tip,first=ff_tip,middle=mf_tip",
    "grasp": "a plan.json file",
    "contact_law": "resolved or paper",
    "volume_term": "element or nodal",
    "out": "a folder",
}


def check_option(key: str, value: object, name: str | None = None) -> object:
    """The value of the plan option or material parameter ``key`` checked for its kind (text, a
    boolean, a number) and its physical range (:data:`~softgrasp.model.ranges.RANGES`); None
    stays None where the option is optional. ConfigError names ``name`` (default ``key``), the
    kind or range expected and the value."""
    label = key if name is None else name
    if value is None and key in PLAN_DEFAULTS and PLAN_DEFAULTS[key] is None:
        return None
    if key in TEXT_OPTIONS:
        if not isinstance(value, str):
            raise ConfigError(f"{label} must be text ({TEXT_OPTIONS[key]}), got {value!r}")
        if key == "units":
            check_units(value, label)
        return value
    if key == "reorient":
        if not isinstance(value, bool):
            raise ConfigError(f"{label} must be true or false, got {value!r}")
        return value
    if key not in RANGES:
        raise ConfigError(f"unknown option {label}")
    return RANGES[key].check(label, value)


def check_inputs(options: Mapping[str, object]) -> None:
    """What can be checked of merged plan ``options`` without meshing: the object (units on a
    built-in object, a shape's text and size) and the material (a preset or key=value list
    parsed, a material file read), each error naming the value."""
    from softgrasp.model.material import parse_material
    from softgrasp.model.objects import check_object

    check_object(str(options["object"]), check_units(options.get("units", "m")))
    spec = options.get("material")
    if options.get("density") is not None and options.get("mass") is not None:
        raise ConfigError("give the object's density (--density) or its mass (--mass), not both")
    if isinstance(spec, str):
        if is_material_file(spec):
            read_material_file(spec)
        else:
            parse_material(spec, need_mass=options.get("density") is None and options.get("mass") is None)


def scheduler_address(text: str) -> str:
    """``text`` when it reads as a Dask scheduler's address, ``[PROTOCOL://]HOST:PORT`` (protocol
    tcp, tls, ucx, ws or wss; port 1-65535), or ``inproc://...``; ConfigError otherwise."""
    import re

    addr = str(text).strip()
    if re.fullmatch(r"inproc://\S+", addr):
        return addr
    m = re.fullmatch(r"(?:(tcp|tls|ucx|ws|wss)://)?(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9._-]+):(\d{1,5})", addr)
    if not m or not 1 <= int(m.group(3)) <= 65535:
        raise ConfigError(
            f"--scheduler must be a Dask scheduler's address tcp://HOST:PORT (or HOST:PORT), got {text!r}"
        )
    return addr


def material_file(spec: str | None) -> MaterialFile | None:
    """The material file named by a ``material`` option, or None for a preset or key=value list."""
    if spec is None or not is_material_file(spec):
        return None
    return read_material_file(spec)


def load_body(
    object_name: str,
    mesh_size: float | None = None,
    material: str | Material | None = None,
    *,
    reorient: bool = False,
    mfile: MaterialFile | None = None,
    overrides: Mapping[str, float] | None = None,
    scale: float = 1.0,
    volume: str = "element",
) -> Body:
    """The object's body (:func:`load_placed_body`)."""
    return load_placed_body(
        object_name, mesh_size, material, reorient=reorient, mfile=mfile, overrides=overrides, scale=scale,
        volume=volume,
    )[0]  # fmt: skip


def _checked_overrides(overrides: Mapping[str, float] | None) -> dict[str, float]:
    if not overrides:
        return {}
    unknown = sorted(set(overrides) - set(MATERIAL_OVERRIDES))
    if unknown:
        raise ConfigError(f"unknown material parameter(s) {unknown}; known: {list(MATERIAL_OVERRIDES)}")
    ov: dict[str, float] = {}
    for k, v in overrides.items():
        if v is None:
            continue
        if isinstance(v, bool) or not isinstance(v, numbers.Real):
            raise ConfigError(f"material parameter {k} must be a number, got {v!r}")
        ov[k] = float(v)
    for k in ("mass", "a2", "a3"):  # (the material checks E, nu and density itself)
        if k in ov:
            RANGES[k].check(f"material parameter {k}", ov[k], MaterialError)
    if "density" in ov and "mass" in ov:
        raise ConfigError("give the object's density (--density) or its mass (--mass), not both")
    return ov


def _warn(message: str) -> None:
    import warnings

    from softgrasp.errors import SoftgraspWarning

    warnings.warn(message, SoftgraspWarning, stacklevel=4)


def load_placed_body(
    object_name: str,
    mesh_size: float | None = None,
    material: str | Material | None = None,
    *,
    reorient: bool = False,
    mfile: MaterialFile | None = None,
    overrides: Mapping[str, float] | None = None,
    scale: float = 1.0,
    volume: str = "element",
    refinement: LocalRefinement | None = None,
) -> tuple[Body, NDArray[np.float64]]:
    """The object's body: its mesh (a mesh file's coordinates times ``scale`` in metres), its
    material (the object's default, a :class:`Material`, a preset or key=value list, or a material
    file ``mfile`` already read from ``material``) and the ``overrides`` (``density`` or ``mass``
    set the mass); and the transform (4, 4) from the source's coordinates to the body's mesh
    (:func:`~softgrasp.model.objects.make_placed_object`).

    A material given with its own density or mass decides the mass; a preset, or a file or
    :class:`Material` without a density, keeps a built-in object's mass. A mesh file or a shape
    (``ball:R`` ...: no mass of its own either) given without a material takes
    :data:`~softgrasp.model.objects.FILE_MATERIAL` (the rubber preset's E and nu; 1000 kg/m^3
    unless ``density`` or ``mass`` is given), and a mesh file whose material has no density,
    1000 kg/m^3: each default with a :class:`~softgrasp.errors.SoftgraspWarning` (none for a shape
    given its density or mass). A shape whose material has no density is refused (ConfigError
    naming ``--density`` and ``--mass``). ``volume``: the body's volume term
    (:attr:`~softgrasp.physics.body.Body.volume`). ``refinement``: finer elements near points
    of a built-in object or a shape (:func:`~softgrasp.model.objects.make_placed_object`).
    """
    from softgrasp.model.material import Polynomial, check_given, parse_material
    from softgrasp.model.objects import FILE_MATERIAL, OBJECTS, is_mesh_file, make_placed_object
    from softgrasp.physics.body import build_body

    mesh, mat, mass, transform = make_placed_object(
        object_name, mesh_size, reorient=reorient, scale=scale, refinement=refinement
    )
    ov = _checked_overrides(overrides)
    mass_given = "density" in ov or "mass" in ov
    file = is_mesh_file(object_name)
    label = Path(object_name).name if file else object_name
    what_object = f"the mesh file {label}" if file else f"the shape {label}"
    own_mass = object_name in OBJECTS  # a built-in object; a file or a shape has no mass of its own
    no_density = ""  # what was given without a density, where the object needs one
    if isinstance(material, Material):
        mat = material
        if mat.density is not None:
            mass = None
        elif mass is None:
            no_density = "the material has no density"
    elif material is not None and is_material_file(material):
        mf = mfile if mfile is not None else read_material_file(material)
        if mf.material is not None:
            mat = mf.material
            if mat.density is not None:
                mass = None
            elif mass is None and mf.mass is None:
                no_density = f"material file {mf.path} has no density_kg_m3"
        if mf.mass is not None:
            mass = mf.mass
    elif material is not None:
        mat, spec_mass = parse_material(material, need_mass=not mass_given)
        if spec_mass is not None:
            mass = spec_mass
        elif "density" in material:
            mass = None
    elif file or (not own_mass and not mass_given):  # a shape given its mass: rubber's E, nu, silently
        water = float(FILE_MATERIAL.density or 0.0)
        what = f"rubber's stiffness (E = {mat.E / 1e3:.4g} kPa, nu = {mat.nu:g})"
        if not mass_given:
            what += f" and the density of water, {water:g} kg/m^3 ({water * mesh.volume * 1e3:.4g} g)"
        _warn(
            f"{what_object} is given without a material: softgrasp takes {what}; give --material "
            "(a preset, E=..,nu=.. or a calibrate .toml)"
            + ("" if mass_given else " and --density KG_M3 or --mass KG")
        )
    if no_density and not mass_given:
        if not file:
            raise ConfigError(
                f"{no_density}; the object {object_name!r} needs one for its mass: give --density KG_M3 "
                "or --mass KG (API: density_kg_m3=, mass_kg=)"
            )
        water = float(FILE_MATERIAL.density or 0.0)
        mat = mat.with_density(water)
        _warn(
            f"{no_density}: softgrasp takes the density of water, {water:g} kg/m^3, for {label} "
            f"({water * mesh.volume * 1e3:.4g} g); give --density KG_M3 or --mass KG"
        )
    if ov:
        law = mat.law
        if "a2" in ov or "a3" in ov:
            base = law.describe() if isinstance(law, Polynomial) else {}
            law = Polynomial(
                ov.get("a2", float(base.get("a2", 0.0))), ov.get("a3", float(base.get("a3", 0.0)))
            )
        density = ov.get("density", mat.density)
        mat = Material(ov.get("E", mat.E), ov.get("nu", mat.nu), density, law, mat.name)
        if "density" in ov:
            mass = None
        if "mass" in ov:
            mass = ov["mass"]
    check_given(mat)
    rho = mat.density if mass is None else mass / mesh.volume
    r = RANGES["density"]
    if rho is not None and not r.contains(rho):
        given = "density" if mass is None else f"mass {mass:.4g} kg in its {mesh.volume * 1e6:.4g} cm^3"
        raise MaterialError(
            f"the object's {given} is a mean density of {rho:.4g} kg/m^3, outside {r.text} ({r.why}); "
            "give a density or mass in range"
        )
    return build_body(mesh, mat, mass=mass, volume=volume), transform


def hand_model(
    name: str,
    fingertips: str | Mapping[str, str] | None = None,
    radius: float | None = None,
    reach: Mapping[str, float | None] | None = None,
):
    """The hand model named by ``hand``: a packaged hand (``shadow_like``, ``parallel_jaw``), a
    URDF or MJCF file, or none; ``fingertips`` maps finger names to links (``thumb=LINK,...``),
    ``radius`` [m] overrides the fingertip spheres', ``reach`` (``min_spread``, ``max_spread``,
    ``max_aperture`` [m], None: the hand's) overrides the hand's layout limits."""
    from dataclasses import replace as _replace

    from softgrasp.hand.chain import parse_fingertips
    from softgrasp.hand.kinematics import HandModel
    from softgrasp.hand.urdf import PACKAGED

    if name == "none":
        return None
    mapping = parse_fingertips(fingertips) if isinstance(fingertips, str) else fingertips
    if name in PACKAGED:
        if mapping is not None:
            raise ConfigError(
                f"--fingertips maps the fingertips of a hand file; the packaged {name} has its own"
            )
        default = name == "shadow_like" and radius is None
        hand = HandModel.default() if default else HandModel.packaged(name, radius)
    else:
        from softgrasp.io.handfile import read_hand  # (XML parsing: only for a hand file)

        hand = read_hand(name, mapping, radius)
    given = {k: v for k, v in (reach or {}).items() if v is not None}
    if given:
        hand = hand.with_reach(_replace(hand.reach, **given))
    return hand


def contact_params(mfile: MaterialFile | None, mu: float | None, **kw: object) -> ContactParams:
    """Contact parameters: the defaults (and ``kw``), a material file's [contact] over them, then
    ``mu`` when given."""
    from softgrasp.physics.fingertip.params import ContactParams

    params = ContactParams(**kw)  # type: ignore[arg-type]
    if mfile is not None:
        params = mfile.contact_params(params)
    if mu is not None:
        params = replace(params, mu=float(mu))
    return params


def plan_config(options: Mapping[str, object], contact: ContactParams) -> PlanConfig:
    """The planner configuration of merged plan ``options`` (every key of :data:`PLAN_DEFAULTS`)."""
    from softgrasp.grasp.initial import HandLayout
    from softgrasp.grasp.planner import PlanConfig
    from softgrasp.io.planfile import load_plan_grasp

    r = options.get("fingertip_radius")
    reach = {k: options.get(k) for k in ("min_spread", "max_spread", "max_aperture")}
    hand = hand_model(str(options["hand"]), options.get("fingertips"), r, reach)  # type: ignore[arg-type]
    if r is None:  # the hand's fingertip spheres' radius (8 mm for free fingertips)
        r = 0.008 if hand is None else hand.fingertip_radius(hand.grasp_fingers[0])
    given = {k: float(v) for k, v in reach.items() if v is not None}  # type: ignore[arg-type]
    layout = HandLayout(**given) if hand is None and given else None  # free fingertips: the limits given
    return PlanConfig(
        layout=layout,  # type: ignore[arg-type]
        contact=contact,
        fingertip_radius=float(r),  # type: ignore[arg-type]
        step=float(options["step"]),  # type: ignore[arg-type]
        solver=str(options["solver"]),
        safety_factor=float(options["safety_factor"]),  # type: ignore[arg-type]
        hold_time=float(options["hold_time"]),  # type: ignore[arg-type]
        max_squeeze=float(options["max_squeeze"]),  # type: ignore[arg-type]
        refine=int(options["refine"]),  # type: ignore[call-overload]
        hand=hand,
        grasp=None if options.get("grasp") is None else load_plan_grasp(str(options["grasp"])),
        max_pressure=None if options.get("max_pressure") is None else float(options["max_pressure"]),  # type: ignore[arg-type]
        max_strain=None if options.get("max_strain") is None else float(options["max_strain"]),  # type: ignore[arg-type]
    )
