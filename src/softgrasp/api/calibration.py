"""Calibration of the public API: :func:`calibrate` fits the material (to a measured compression
curve) and the fingertip contact law (to a measured indentation curve) by simulating the tests;
its result's :meth:`Calibration.save` writes the files of ``softgrasp calibrate``
(``material.toml``, ``calibration.json`` and a figure per fit)."""

from __future__ import annotations

import time
from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from softgrasp import __version__
from softgrasp.api.objects import SoftObject, load_object
from softgrasp.errors import ConfigError
from softgrasp.model.material import Material

if TYPE_CHECKING:
    from softgrasp.experiments.calibration import CalibrationFit, CompressionData, IndentationData
    from softgrasp.physics.fingertip.params import ContactParams

__all__ = ["Calibration", "calibrate", "check_calibrate", "read_indentation", "fit_summary"]

#: Called with a stage's description; gives a context manager yielding the stage's progress
#: callback (simulated tests so far).
Progress = Callable[[str], AbstractContextManager[Callable[[int], None] | None]]


def fit_summary(fit: CalibrationFit) -> str:
    """The fitted values of a fit, one per line, for people and the figure."""
    units = {"E_Pa": ("E", 1e-3, "kPa"), "gamma_N_s_m2": ("gamma", 1.0, "N s/m^2")}
    rows = []
    for name, p in fit.parameters.items():
        label, scale, unit = units.get(name, (name, 1.0, ""))
        sd = "" if p.stderr != p.stderr else f" +- {p.stderr * scale:.3g}"
        rows.append(f"{label:<19} {p.value * scale:.5g}{sd} {unit} ({p.status})".replace("  (", " ("))
    rows.append(f"rms residual        {fit.residual_rms_N:.3g} N ({fit.relative_rms:.2%} of the peak)")
    rows.append(f"mean |error|        {fit.mean_abs_error_N:.3g} N")
    return "\n".join(rows)


def check_calibrate(
    compression: object,
    indentation: object,
    nu: float | None,
    plate_friction: float = 0.5,
    *,
    steps: int = 16,
    radius_m: float = 0.008,
    speed_m_s: float = 0.005,
    mu: float | None = None,
) -> None:
    """Refuse a calibration without data, and settings outside their physical ranges
    (:data:`~softgrasp.model.ranges.RANGES`): a Poisson's ratio outside (-1, 0.5), platen or
    fingertip friction outside [0, 5], steps, fingertip radius or speed out of range."""
    from softgrasp.model.ranges import check

    if compression is None and indentation is None:
        raise ConfigError("give measured data to fit: --compression DATA.csv and/or --indentation DATA.csv")
    if nu is not None:
        check("nu", nu, "--nu")
    check("plate_friction", plate_friction, "--plate-friction")
    check("compress_steps", steps, "--steps")
    check("radius", radius_m, "--radius")
    check("speed", speed_m_s, "--speed")
    if mu is not None:
        check("mu", mu, "--mu")


def read_indentation(path: str | Path) -> IndentationData:
    """A measured indentation CSV (``penetration_m`` or ``penetration_mm``, ``force_N``, optional
    ``tangential_force_N``), checked (it needs no specimen)."""
    from softgrasp.experiments.calibration import read_indentation_data

    return read_indentation_data(path)


@dataclass(eq=False)
class Calibration:
    """A calibration.

    Attributes
    ----------
    object: the specimen.  material: the calibrated material (named ``calibrated`` after a
    compression fit).  contact: the fitted contact parameters, or None without indentation data.
    fits: the fits by kind (``compression``, ``indentation``).  sources: their data files.
    document: the ``calibration.json`` document.
    """

    object: SoftObject
    material: Material
    contact: ContactParams | None
    fits: dict[str, CalibrationFit]
    sources: dict[str, str]
    document: dict[str, Any]
    _started: float = field(default_factory=time.perf_counter, repr=False)

    @property
    def E_Pa(self) -> float:
        """The calibrated Young's modulus [Pa]."""
        return float(self.material.E)

    @property
    def figures(self) -> list[str]:
        """The figures :meth:`save` writes."""
        return [f"{kind}_fit.png" for kind in self.fits]

    def to_dict(self) -> dict[str, Any]:
        """The ``calibration.json`` document (without its wall time)."""
        return dict(self.document)

    def save(self, out: str | Path, *, started: float | None = None) -> Path:
        """Write a figure per fit, ``material.toml`` and ``calibration.json`` into ``out``,
        replacing the folder's earlier ones whole (:mod:`softgrasp.io.runfolder`: a failure or an
        interrupt leaves them as they were)."""
        from softgrasp.io.runfolder import save_whole

        return save_whole(out, "calibrate", lambda stage: self._write(stage, started, Path(out)))

    def _write(self, out: Path, started: float | None, folder: Path) -> None:
        """The files into ``out``, the files they name relative to ``folder``, where they go."""
        import copy

        from softgrasp.io.atomic import write_json
        from softgrasp.io.materialfile import write_material_file
        from softgrasp.io.portable import portable_path
        from softgrasp.viz.plots import plot_calibration

        sources = {k: portable_path(v, folder) for k, v in self.sources.items()}

        for kind, fit in self.fits.items():
            lateral = None
            if kind == "compression":
                xlabel, title = "displacement", "Compression fit"
                if fit.lateral_measured is not None:
                    lateral = (fit.lateral_measured, fit.lateral_fitted)
            else:
                xlabel = "penetration"
                title = f"Indentation fit, R = {self.document['fits'][kind]['radius_m'] * 1e3:.3g} mm"
            plot_calibration(
                out / f"{kind}_fit.png",
                fit.x,
                fit.measured,
                fit.fitted,
                xlabel=xlabel,
                title=f"{title} ({Path(self.sources[kind]).name})",
                summary=fit_summary(fit),
                lateral=lateral,
            )
        write_material_file(
            out / "material.toml",
            self.material,
            self.contact,
            comment=f"softgrasp calibrate: {', '.join(f'{k} {sources[k]}' for k in self.fits)}\n"
            "use with --material FILE in plan, indent, compress and execute",
        )
        wall = time.perf_counter() - (self._started if started is None else started)
        doc = {**copy.deepcopy(self.document), "wall_time_s": wall}
        doc["specimen"] = self.object.to_dict(folder)
        for kind, fit in doc.get("fits", {}).items():
            fit["data"] = sources.get(kind, fit.get("data"))
        write_json(out / "calibration.json", doc)


def calibrate(
    obj: SoftObject | str = "cube",
    *,
    compression: str | Path | None = None,
    indentation: str | Path | IndentationData | None = None,
    nu: float | None = None,
    law: str = "polynomial",
    plate_friction: float = 0.5,
    steps: int = 16,
    radius_m: float = 0.008,
    speed_m_s: float = 0.005,
    mu: float | None = None,
    progress: Progress | None = None,
    echo: Callable[[str], None] | None = None,
) -> Calibration:
    """Fit the material of ``obj`` (the specimen) to a measured ``compression`` curve and/or the
    fingertip contact law to a measured ``indentation`` curve.

    Parameters
    ----------
    compression:
        CSV: ``displacement_m|displacement_mm,force_N`` or ``strain,stress_Pa|_kPa|_MPa``; an
        optional ``lateral_strain`` column fits nu too.
    indentation:
        CSV: ``penetration_m|penetration_mm,force_N`` (optional ``tangential_force_N``: mu is fitted
        too), or the data already read (:func:`read_indentation`).
    nu:
        Poisson's ratio when not fitted (default the object's material's).
    law:
        Spring law fitted: ``polynomial`` or ``linear``.
    plate_friction, steps:
        Friction of the compression platens; increments of each simulated compression.
    radius_m, speed_m_s, mu:
        Fingertip radius [m], indentation speed [m/s], fingertip friction (default the material
        file's, else 0.8).
    progress:
        Gives a progress callback per fit (see :data:`Progress`).
    echo:
        Called with lines for people as the calibration goes (the data read, each fit's summary).
    """
    from softgrasp.experiments.calibration import (
        fit_compression,
        fit_indentation,
        read_compression_data,
        specimen_geometry,
    )
    from softgrasp.io.options import contact_params
    from softgrasp.physics.body import build_body

    started = time.perf_counter()
    say = echo if echo is not None else (lambda line: None)
    stage = progress if progress is not None else (lambda desc: nullcontext(None))
    check_calibrate(
        compression, indentation, nu, plate_friction, steps=steps, radius_m=radius_m, speed_m_s=speed_m_s,
        mu=mu,
    )
    ind_data = read_indentation(indentation) if isinstance(indentation, str | Path) else indentation
    if not isinstance(obj, SoftObject):
        obj = load_object(obj)
    body = obj.body
    mesh, material, mass = body.mesh, body.material, body.total_mass
    # The density goes into material.toml only when the user gave one: otherwise a built-in
    # object planned with the file keeps its own mass.
    density = material.density if obj.density_given else None
    comp_data: CompressionData | None = None
    if compression is not None:
        comp_data = read_compression_data(compression, *specimen_geometry(mesh))
    say(f"specimen {obj.summary()}")
    fits: dict[str, CalibrationFit] = {}
    sources: dict[str, str] = {}
    if comp_data is not None:
        top = float(comp_data.displacement_m.max())
        say(
            f"compression: {len(comp_data.force_N)} points from {compression}, up to "
            f"{top * 1e3:.3g} mm ({top / comp_data.height_m:.0%})"
        )
        with stage("fit compression") as update:
            fitted, fit = fit_compression(
                mesh,
                comp_data,
                nu=nu if nu is not None else material.nu,
                mass=mass,
                law=law,
                plate_friction=plate_friction,
                steps=steps,
                progress=update,
                volume=body.volume,
            )
        material = Material(fitted.E, fitted.nu, density, fitted.law, name="calibrated")
        fits["compression"], sources["compression"] = fit, str(compression)
        say(fit_summary(fit))
    else:
        material = Material(material.E, material.nu, density, material.law, name=material.name)
    contact = None
    if ind_data is not None:
        say(f"indentation: {len(ind_data.force_N)} points from {ind_data.source}")
        ibody = build_body(mesh, material, mass=mass, volume=body.volume)
        with stage("fit indentation") as update:
            contact, ifit = fit_indentation(
                ibody,
                ind_data,
                params=contact_params(obj.material_file, mu),
                radius=radius_m,
                speed=speed_m_s,
                progress=update,
            )
        fits["indentation"], sources["indentation"] = ifit, str(ind_data.source)
        say(fit_summary(ifit))
    for fit in fits.values():
        for note in fit.notes:
            say(f"note: {note}")
    doc: dict[str, Any] = {
        "schema": "softgrasp.calibration/1",
        "softgrasp_version": __version__,
        "specimen": obj.to_dict(),
        "E_Pa": material.E,
        "nu": material.nu,
        "law": material.law.describe(),
        "residual": {k: {"rms_N": f.residual_rms_N, "relative_rms": f.relative_rms} for k, f in fits.items()},
    }
    if "indentation" in fits:
        doc["mean_abs_error_N"] = fits["indentation"].mean_abs_error_N
        assert contact is not None
        doc["contact"] = contact.describe()
    details = {
        k: {
            "data": sources[k],
            "points": len(f.x),
            "converged": f.converged,
            "parameters": {n: p.describe() for n, p in f.parameters.items()},
            "correlation": f.correlation,
            "residual_rms_N": f.residual_rms_N,
            "mean_abs_error_N": f.mean_abs_error_N,
            "relative_rms": f.relative_rms,
            "simulations": f.simulations,
            "wall_time_s": f.wall_time_s,
            "notes": list(f.notes),
        }
        for k, f in fits.items()
    }
    if comp_data is not None:
        details["compression"].update(
            {"plate_friction": plate_friction, "height_m": comp_data.height_m, "area_m2": comp_data.area_m2}
        )
    if ind_data is not None:
        details["indentation"].update({"radius_m": radius_m, "speed_m_s": speed_m_s})
    doc["fits"] = details
    return Calibration(obj, material, contact, fits, sources, doc, _started=started)
