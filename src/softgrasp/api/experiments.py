"""Simulated material tests of the public API: :func:`compress` (an object between rigid plates,
paper Fig. 8-9) and :func:`indent` (one fingertip pressed into it, paper Fig. 10-11), whose
results' ``save(dir)`` write the files of ``softgrasp compress`` and ``softgrasp indent``."""

from __future__ import annotations

import csv
import io
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from softgrasp import __version__
from softgrasp.api.objects import SoftObject, load_object
from softgrasp.errors import ConfigError

if TYPE_CHECKING:
    from softgrasp.experiments.compression import CompressionResult
    from softgrasp.experiments.indentation import IndentationResult
    from softgrasp.physics.fingertip.params import ContactParams

__all__ = [
    "Compression",
    "compress",
    "ForceCurve",
    "read_force_curve",
    "Indentation",
    "indent",
    "contact_mesh",
]


def _csv(header: list[str], rows: Any) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    for row in rows:
        w.writerow(row)
    return buf.getvalue()


@dataclass(eq=False)
class Compression:
    """A simulated compression test.

    Attributes
    ----------
    object: the specimen.  result: the force-displacement record
    (:class:`~softgrasp.experiments.compression.CompressionResult`: ``apparent_E_Pa``,
    ``force_N``, ``strain``, ``stress_Pa`` ...).  parameters: the test's settings (SI units).
    """

    object: SoftObject
    result: CompressionResult
    parameters: dict[str, Any]
    _started: float = field(default_factory=time.perf_counter, repr=False)

    @property
    def apparent_E_Pa(self) -> float:
        """Young's modulus from the initial slope of the stress-strain curve [Pa]."""
        return float(self.result.apparent_E_Pa)

    @property
    def peak_force_N(self) -> float:
        """Largest plate force [N]."""
        return float(self.result.force_N.max())

    def to_dict(self, started: float | None = None, folder: str | Path | None = None) -> dict[str, Any]:
        """The ``compress.json`` document; ``wall_time_s`` counts from ``started`` (a
        :func:`time.perf_counter` value; default when :func:`compress` began); a mesh file named
        relative to ``folder``, the output folder (:meth:`SoftObject.to_dict`)."""
        res = self.result
        return {
            "schema": "softgrasp.compress/1",
            "softgrasp_version": __version__,
            "object": self.object.to_dict(folder),
            "parameters": {
                **self.parameters,
                "height_m": res.height_m,
                "area_m2": res.area_m2,
                "fit_strain": res.fit_strain,
                "solver": "static Newton, sparse Jacobian, energy line search",
            },
            "apparent_E_Pa": res.apparent_E_Pa,
            "apparent_nu": res.apparent_nu,
            "peak_force_N": float(res.force_N.max()),
            "peak_stress_Pa": float(res.stress_Pa.max()),
            "newton_iterations": res.newton_iterations.tolist(),
            "wall_time_s": time.perf_counter() - (self._started if started is None else started),
        }

    def save(self, out: str | Path, *, started: float | None = None) -> Path:
        """Write ``compress.csv``, ``compress.json`` and ``compress.png`` into ``out``, replacing the
        folder's earlier ones whole (:mod:`softgrasp.io.runfolder`)."""
        from softgrasp.io.runfolder import save_whole

        return save_whole(out, "compress", lambda stage: self._write(stage, started, Path(out)))

    def _write(self, out: Path, started: float | None, folder: Path) -> None:
        from softgrasp.io.atomic import write_json, write_text
        from softgrasp.viz.plots import plot_stress_strain

        res = self.result
        rows = zip(res.displacement_m, res.force_N, res.strain, res.stress_Pa, strict=True)
        header = ["displacement_m", "force_N", "strain", "stress_Pa"]
        write_text(out / "compress.csv", _csv(header, ([f"{v:.9g}" for v in row] for row in rows)))
        write_json(out / "compress.json", self.to_dict(started, folder))
        plot_stress_strain(
            out / "compress.png",
            res.strain,
            res.stress_Pa,
            apparent_E_Pa=res.apparent_E_Pa,
            title=f"Compression of the {self.object.name} ({self.object.material.name})",
            linear_E_Pa=self.object.material.E,
        )


def compress(
    obj: SoftObject | str = "sphere",
    *,
    strain: float = 0.3,
    steps: int = 30,
    plate_friction: float = 0.5,
    progress: Callable[[float], None] | None = None,
) -> Compression:
    """Compress ``obj`` between rigid plates to the engineering ``strain`` in ``steps`` load
    increments (static Newton per increment). ``plate_friction``: the platens' friction
    coefficient (0.5, rubber on steel: faces stick at rest; 0 is a lubricated test)."""
    from softgrasp.experiments.compression import compression_test

    started = time.perf_counter()
    from softgrasp.model.ranges import check

    check("plate_friction", plate_friction, "--plate-friction")
    check("compress_steps", steps, "--steps")
    check("strain", strain, "--strain")
    if not isinstance(obj, SoftObject):
        obj = load_object(obj)
    res = compression_test(
        obj.body, strain=strain, steps=steps, plate_friction=plate_friction, progress=progress
    )
    params = {
        "strain": strain,
        "steps": steps,
        "plate_friction": plate_friction,
        "mesh_size_m": obj.mesh_size_m,
    }
    return Compression(obj, res, params, _started=started)


@dataclass(frozen=True)
class ForceCurve:
    """A measured force-penetration curve: its file, penetrations [m] and forces [N]."""

    path: str
    penetration_m: Any
    force_N: Any

    @property
    def points(self) -> int:
        """Number of measured points."""
        return int(self.penetration_m.size)


def read_force_curve(path: str | Path, depth_m: float) -> ForceCurve:
    """A measured force-penetration CSV (header: ``penetration_m`` or ``penetration_mm``, and
    ``force_N``), its penetrations within 0..``depth_m``."""
    from softgrasp.experiments.indentation import read_force_curve as read

    pen, force = read(path, max_penetration=depth_m)
    return ForceCurve(str(path), pen, force)


@dataclass(eq=False)
class Indentation:
    """A simulated indentation: one fingertip pressed into the object resting on the table.

    Attributes
    ----------
    object: the object.  result: the record (:class:`~softgrasp.experiments.indentation.
    IndentationResult`).  contact: the contact parameters.  radius_m: the fingertip radius.
    steps: the load increments.  measured: the curve compared with, or None.
    mean_abs_error_N: mean absolute force error against it, or None.
    """

    object: SoftObject
    result: IndentationResult
    contact: ContactParams
    radius_m: float
    steps: int
    rule: str
    measured: ForceCurve | None = None
    mean_abs_error_N: float | None = None
    _started: float = field(default_factory=time.perf_counter, repr=False)

    @property
    def force_at_depth_N(self) -> float:
        """The force at the full depth [N]."""
        return float(self.result.force_N[-1])

    def to_dict(self, started: float | None = None, folder: str | Path | None = None) -> dict[str, Any]:
        """The ``indent.json`` document; ``wall_time_s`` counts from ``started`` (default when
        :func:`indent` began); the mesh and data files named relative to ``folder``, the output
        folder (:func:`~softgrasp.io.portable.portable_path`)."""
        from softgrasp.io.portable import portable_path

        res = self.result
        report: dict[str, Any] = {
            "schema": "softgrasp.indent/1",
            "softgrasp_version": __version__,
            "object": self.object.to_dict(folder),
            "parameters": {
                "depth_m": res.depth_m,
                "radius_m": self.radius_m,
                "speed_m_s": res.speed_m_s,
                "steps": self.steps,
                "increment_m": res.depth_m / self.steps,
                "mesh_size_m": self.object.mesh_size_m,
                "table_mu": res.table_mu,
                "point_m": res.point_m.tolist(),
                "point_shift_m": res.point_shift_m,
                "surface_z_m": res.surface_z_m,
                "first_contact_travel_m": res.first_contact_travel_m,
                "placement": "turned onto its most stable facet" if res.turned else "as meshed",
                "penetration": "fingertip travel since first detected contact with the settled object",
                "solver": "quasi-static: a static Newton solve per increment, after settling on the table",
            },
            "contact": self.contact.describe(),
            "fingertip": res.fingertip.describe(),
            "K_N_m1.5": res.K_N_m1_5,
            "peak_force_N": res.peak_force_N,
            "force_at_depth_N": float(res.force_N[-1]),
            "contact_depth_m": res.contact_depth_m.tolist(),
            "newton_iterations": res.newton_iterations.tolist(),
            "split_increments": res.halvings,
        }
        if self.measured is not None:
            data = self.measured.path
            report["data_file"] = data if folder is None else portable_path(data, folder)
            report["measured_points"] = self.measured.points
            report["mean_abs_error_N"] = self.mean_abs_error_N
        report["wall_time_s"] = time.perf_counter() - (self._started if started is None else started)
        return report

    def save(self, out: str | Path, *, started: float | None = None) -> Path:
        """Write ``indent.csv``, ``indent.json`` and ``indent.png`` into ``out``, replacing the
        folder's earlier ones whole (:mod:`softgrasp.io.runfolder`)."""
        from softgrasp.io.runfolder import save_whole

        return save_whole(out, "indent", lambda stage: self._write(stage, started, Path(out)))

    def _write(self, out: Path, started: float | None, folder: Path) -> None:
        from softgrasp.io.atomic import write_json, write_text
        from softgrasp.viz.plots import plot_force_penetration

        res = self.result
        header = ["time_s", "penetration_m", "force_N", "normal_force_N", "tangential_force_N", "contacts"]
        cols = (res.time_s, res.penetration_m, res.force_N, res.normal_force_N, res.tangential_force_N)
        rows = ([*(f"{v:.9g}" for v in vals), int(n)] for *vals, n in zip(*cols, res.contacts, strict=True))
        write_text(out / "indent.csv", _csv(header, rows))
        write_json(out / "indent.json", self.to_dict(started, folder))
        m = self.object.material
        title = f"Indentation of the {self.object.name} ({m.name}), R = {self.radius_m * 1e3:.3g} mm"
        if self.object.refinement is not None:
            title += f"\non a contact mesh of {self.object.refinement.size_m * 1e3:.2g} mm elements"
        measured = None if self.measured is None else (self.measured.penetration_m, self.measured.force_N)
        plot_force_penetration(
            out / "indent.png",
            res.penetration_m,
            res.force_N,
            title=title,
            measured=measured,
            mean_abs_error_N=self.mean_abs_error_N,
        )


#: The automatic local element size under an indenting fingertip, as a share of the Hertz contact
#: radius at the depth; the refined zone reaches :data:`CONTACT_ZONE` contact radii. Measured, force
#: over Hertz's (at the fingertip and the table for the sphere; a half-space for the cube), with the
#: per-tet volume term: the sphere pressed 3 mm, 1.037 / 1.031 / 1.016 / 1.003 on the 16 / 12 / 8 /
#: 6 mm meshes, 1.043-1.055 with shares 2 % apart on the 16 mm one; the foam cube pressed 0.5 mm,
#: 0.973 / 0.952 / 0.969 / 0.953 on its 8.3 to 4.2 mm meshes, 0.954-0.986 with shares 2 % apart.
#: The nodal term scatters more with the mesh's details: 0.93-1.02 on the 16 mm sphere with shares
#: 2 % apart; on a 20 mm ball pressed 1 mm (a = 2.83 mm) 0.97-1.07 at elements of 1.40 to 0.70 mm.
CONTACT_SHARE = 1.0 / 3.0
CONTACT_ZONE = 2.0


def contact_mesh(
    obj: SoftObject, depth_m: float, radius_m: float, size_m: float | str
) -> tuple[SoftObject, tuple[float, float] | None]:
    """``obj`` meshed again with elements of ``size_m`` [m] (``"auto"``: :data:`CONTACT_SHARE`
    times ``a = sqrt(R depth)``, the Hertz contact radius of a rigid fingertip of radius R pressed
    ``depth_m`` into a half-space, which bounds the real one) within :data:`CONTACT_ZONE` times
    ``a`` of its top and of its bottom (the table's contact), above and below its centroid as
    generated, and the point (x, y) [m] to press at: the top's, once the new mesh rests on the
    table (its pose turns by about the tilt of the fine bottom's facets: a degree or two).
    ``"auto"`` on a mesh file (softgrasp does not mesh it) or on an object meshed no coarser than
    that already: ``obj`` itself and None (the point:
    :func:`~softgrasp.experiments.indentation.indentation_test`'s own)."""
    import math

    import numpy as np

    from softgrasp.api.objects import refined
    from softgrasp.experiments.indentation import surface_height
    from softgrasp.model.mesh.generate import LocalRefinement
    from softgrasp.model.objects import element_size, is_mesh_file
    from softgrasp.model.ranges import UNITS, check

    a = math.sqrt(radius_m * depth_m)
    if isinstance(size_m, str):
        if size_m != "auto":
            raise ConfigError(f"the contact mesh size must be a length in metres or auto, got {size_m!r}")
        size = CONTACT_SHARE * a
        if is_mesh_file(obj.source) or size >= element_size(obj.source, obj.mesh_size_m, UNITS[obj.units]):
            return obj, None  # a mesh file, or elements that resolve the patch as they are
    else:
        size = check("mesh_size", size_m, "the contact mesh size")
    mesh = obj.body.mesh
    x = np.asarray(mesh.points)
    R, shift = obj.transform[:3, :3], obj.transform[:3, 3]
    source = (x - shift) @ R  # the body's rigid placement undone
    centre = (np.asarray(mesh.centroid, dtype=float) - shift) @ R
    top, _ = surface_height(source, mesh.facets, centre[:2])
    bottom = float(source[:, 2].min())
    points = ((float(centre[0]), float(centre[1]), top), (float(centre[0]), float(centre[1]), bottom))
    new = refined(obj, LocalRefinement(points, size, max(CONTACT_ZONE * a, 2.0 * size)))
    pressed = new.transform @ np.append(points[0], 1.0)
    return new, (float(pressed[0]), float(pressed[1]))


def check_indent(
    mu: float | None,
    steps: int | None,
    *,
    depth_m: float = 0.005,
    radius_m: float = 0.008,
    speed_m_s: float = 0.005,
) -> None:
    """Refuse settings outside their physical ranges (:data:`~softgrasp.model.ranges.RANGES`):
    friction outside [0, 5], a step count outside 1..100000, depth, radius or speed out of range."""
    from softgrasp.model.ranges import check

    if mu is not None:
        check("mu", mu, "--mu")
    if steps is not None:
        check("indent_steps", steps, "--steps")
    check("depth", depth_m, "--depth")
    check("radius", radius_m, "--radius")
    check("speed", speed_m_s, "--speed")


def indent(
    obj: SoftObject | str = "cube",
    *,
    depth_m: float = 0.005,
    radius_m: float = 0.008,
    speed_m_s: float = 0.005,
    steps: int | None = None,
    mu: float | None = None,
    rule: str = "patch",
    contact_law: str = "resolved",
    data: str | Path | ForceCurve | None = None,
    contact_mesh_size_m: float | str | None = "auto",
    progress: Callable[[float], None] | None = None,
) -> Indentation:
    """Press a fingertip of radius ``radius_m`` [m] ``depth_m`` [m] into ``obj`` (beyond first
    contact) at ``speed_m_s`` in ``steps`` increments (default about 0.25 mm each, at least 10),
    quasi-statically after the object settled on the table.

    ``mu``: fingertip friction (default the material file's, else 0.8). ``rule``: ``patch`` or
    ``facet`` (the paper's literal rule). ``contact_law``: ``resolved`` (the object's compliance
    counted once) or ``paper`` (K delta^n, Eq. 9-11). ``data``: a measured force-penetration curve to compare
    with (:func:`read_force_curve`, or its file). ``contact_mesh_size_m``: mesh the object again
    with elements of this size [m] where the fingertip presses and where it rests on the table,
    so that the mesh resolves the contact patches (:func:`contact_mesh`); the fingertip then
    presses where the refined zone came to rest. ``"auto"`` (the default): a third of the Hertz
    contact radius at the depth, for an object softgrasp meshes under the ``resolved`` law; a
    mesh file, or the ``paper`` law (which reproduces the paper's run on its mesh), is indented
    on the mesh as it is. ``None``: the object's own mesh.
    """
    from softgrasp.experiments.indentation import default_steps, indentation_test, mean_abs_force_error
    from softgrasp.io.options import contact_params

    started = time.perf_counter()
    check_indent(mu, steps, depth_m=depth_m, radius_m=radius_m, speed_m_s=speed_m_s)
    if not isinstance(obj, SoftObject):
        obj = load_object(obj)
    if contact_law not in ("resolved", "paper"):
        raise ConfigError(f"contact_law must be resolved or paper, got {contact_law!r}")
    params = contact_params(obj.material_file, mu, rule=rule, law=contact_law)
    measured = read_force_curve(data, depth_m) if isinstance(data, str | Path) else data
    n = steps if steps is not None else default_steps(depth_m)
    point = None
    # the paper's law reproduces the paper's run on the object's own mesh
    if contact_mesh_size_m is not None and not (contact_mesh_size_m == "auto" and contact_law == "paper"):
        obj, point = contact_mesh(obj, depth_m, radius_m, contact_mesh_size_m)
    res = indentation_test(
        obj.body,
        depth=depth_m,
        radius=radius_m,
        speed=speed_m_s,
        steps=n,
        params=params,
        point=point,
        progress=progress,
    )
    error = None
    if measured is not None:
        error = mean_abs_force_error(res, measured.penetration_m, measured.force_N)
    return Indentation(obj, res, params, radius_m, n, rule, measured, error, _started=started)
