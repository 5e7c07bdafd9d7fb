"""Planning a grasp: :func:`plan` and its result :class:`Plan`, whose :meth:`Plan.save` writes the
files of ``softgrasp plan --out DIR``.

A plan closes the three fingertips of the hand on the object in small increments until the
object, released from the table, is held (paper Sec. 2, 4.3); its set-points are the fingertips'
normal forces in the held state.
"""

from __future__ import annotations

import csv
import io
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from softgrasp.api.objects import SoftObject, load_object
from softgrasp.errors import ConfigError, SoftgraspError
from softgrasp.io.options import PLAN_DEFAULTS, check_inputs, check_option
from softgrasp.model.ranges import check_volume_term

if TYPE_CHECKING:
    from softgrasp.grasp.planner import GraspPlan, PlanConfig
    from softgrasp.hand.kinematics import HandModel
    from softgrasp.viz.worker import FigureWorker

__all__ = ["Plan", "plan", "plan_options", "PLAN_FILES"]

#: The files :meth:`Plan.save` (``softgrasp plan --out DIR``) writes.
PLAN_FILES = (
    "plan.json",
    "history.csv",
    "object.vtu",
    "closing.pvd",
    "frames.npz",
    "forces.png",
    "force_penetration.png",
    "grasp.png",
)


def plan_options(given: Mapping[str, object], config_file: str | Path | None = None) -> dict[str, object]:
    """The plan options (every key of :data:`~softgrasp.io.options.PLAN_DEFAULTS`): the ``given``
    ones (None or False: not given) over a TOML ``config_file``'s over the defaults, each checked
    for its kind and physical range (:func:`~softgrasp.io.options.check_option`)."""
    conf: dict[str, object] = {}
    if config_file is not None:
        from softgrasp.io.tomlfile import read_toml

        raw = read_toml(config_file, "config file")
        conf = {k.replace("-", "_"): v for k, v in raw.items()}
        unknown = sorted(set(conf) - set(PLAN_DEFAULTS))
        if unknown:
            raise ConfigError(
                f"config file {config_file}: unknown key(s) {', '.join(unknown)}; "
                f"known: {', '.join(sorted(PLAN_DEFAULTS))}"
            )
    merged: dict[str, object] = {}
    from_config = set()
    for key, default in PLAN_DEFAULTS.items():
        value = given.get(key)
        name = f"--{key.replace('_', '-')}"
        if value is None or value is False:  # (0.0 == False: test identity, not equality)
            value = conf.get(key, default)
            name = f"config file {config_file}: {key}" if key in conf else key
            from_config |= {key} & set(conf)
        merged[key] = check_option(key, value, name)
    try:
        check_inputs(merged)
    except SoftgraspError as exc:  # the object or material of a config file: name the file
        if from_config & {"object", "units", "material"}:
            raise type(exc)(f"config file {config_file}: {exc}") from None
        raise
    if merged["contact_law"] not in ("resolved", "paper"):
        raise ConfigError(f"contact_law must be resolved or paper, got {merged['contact_law']!r}")
    if merged["solver"] not in ("quasistatic", "dynamic"):
        raise ConfigError(f"solver must be quasistatic or dynamic, got {merged['solver']!r}")
    check_volume_term(merged["volume_term"])
    return merged


@dataclass(eq=False)
class Plan:
    """A planned grasp.

    Attributes
    ----------
    object: the object planned for.
    grasp: the planner's full result (:class:`~softgrasp.grasp.planner.GraspPlan`: initial grasp,
        per-increment history, held state, hand posture).
    config: the planner configuration used.
    options: the plan options (as ``softgrasp plan`` names them; SI units).
    document: the ``plan.json`` document (schema ``softgrasp.plan/2``).
    directory: the folder :meth:`save` last wrote, or None.
    """

    object: SoftObject
    grasp: GraspPlan
    config: PlanConfig
    options: dict[str, object]
    document: dict[str, Any]
    directory: Path | None = None
    _started: float = field(default_factory=time.perf_counter, repr=False)

    @property
    def setpoints_N(self) -> dict[str, float]:
        """Each finger's force set-point [N]: the normal force its force controller closes to
        (``safety_factor`` times the least that holds in softgrasp's model)."""
        return {f["name"]: float(f["setpoint_N"]) for f in self.document["fingers"]}

    @property
    def forces_N(self) -> dict[str, float]:
        """Each finger's total force (normal and friction) in the held state [N]."""
        return {f.name: float(f.force_norm) for f in self.grasp.fingers}

    @property
    def penetration_m(self) -> dict[str, float]:
        """Each fingertip's penetration into the object in the held state [m]."""
        return {f.name: float(f.penetration) for f in self.grasp.fingers}

    @property
    def mu(self) -> float:
        """The fingertip friction coefficient planned with."""
        return float(self.config.contact.mu)

    def table(self) -> str:
        """The set-points as a table for people (the paper's Table 2)."""
        from softgrasp.io.plan_document import plan_table

        return plan_table(self.grasp)

    def to_dict(self) -> dict[str, Any]:
        """The ``plan.json`` document (a copy)."""
        import copy

        return copy.deepcopy(self.document)

    def write_plan_file(self, out: str | Path) -> Path:
        """Write only what execution reads, ``plan.json`` and the placed mesh ``object.vtu`` (with the
        held state's arrays, :mod:`softgrasp.io.paraview`), into ``out`` (the two together,
        :mod:`softgrasp.io.runfolder`); return the path of ``plan.json``."""
        from softgrasp.io.atomic import write_json
        from softgrasp.io.paraview import write_object_vtu
        from softgrasp.io.runfolder import run_folder

        with run_folder(out, "plan", complete=False) as folder:
            write_object_vtu(folder.stage / "object.vtu", self.grasp, self.object.body)
            self.document["object"]["mesh_file"] = "object.vtu"
            _portable_hand(self.document, folder.path)
            write_json(folder.stage / "plan.json", self.document)
        return folder.path / "plan.json"

    def save(
        self, out: str | Path, *, figures: FigureWorker | None = None, started: float | None = None
    ) -> Path:
        """Write the files of ``softgrasp plan --out DIR`` (:data:`PLAN_FILES`) into ``out``,
        replacing the folder's earlier plan files whole (:mod:`softgrasp.io.runfolder`: a failure
        or an interrupt leaves them as they were; files of an earlier plan this one does not
        write, such as robust set-points, are removed; no other file is touched); return ``out``.

        ``figures`` draws the PNGs (default: a worker started here); ``plan.json``'s ``wall_time_s``
        counts from ``started`` (a :func:`time.perf_counter` value; default when :func:`plan` began).
        """
        from softgrasp.io.runfolder import run_folder
        from softgrasp.viz.worker import FigureWorker

        with run_folder(out, "plan") as folder:
            if figures is None:  # (stopped before the folder is committed or cleared)
                with FigureWorker() as worker:
                    self._write(folder.stage, worker, started)
            else:
                self._write(folder.stage, figures, started)
        self.directory = Path(out)
        return Path(out)

    def _write(self, out: Path, figures: FigureWorker, started: float | None) -> None:
        """Write the plan's files into ``out`` (a staging folder)."""
        import numpy as np

        from softgrasp.io.atomic import write_text
        from softgrasp.io.plan_document import HISTORY_HEADER, hand_polylines, history_rows

        g, body, doc = self.grasp, self.object.body, self.document
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(HISTORY_HEADER)
        for row in history_rows(g):
            w.writerow([f"{v:.9g}" if isinstance(v, float) else v for v in row])
        names = [f.name for f in g.fingers]
        figures.draw(
            "plot_plan_forces",
            np.arange(1.0, g.increments + 1.0),
            g.normal_force,
            names,
            out / "forces.png",
            setpoints=g.setpoints,
            held_at=g.held_increment,
            title="Normal forces of the fingers and their set-points",
            quantity="normal force",
        )
        figures.draw(
            "plot_plan_force_penetration", g.penetration, g.force_norm, names, out / "force_penetration.png"
        )
        m = body.material
        figures.draw(
            "plot_grasp_3d",
            g.positions,
            body.mesh.facets,
            g.centres,
            np.full(len(self.grasp.fingers), self.config.fingertip_radius),
            np.array([f.force for f in g.fingers]),
            g.contact_points,
            names,
            out / "grasp.png",
            title=f"Held grasp of the {doc['object']['name']} ({m.name}), mu = {self.mu:g}",
            weight=(g.com, body.total_mass * float(abs(body.gravity[2]))),
            links=hand_polylines(g),
            setpoints=g.setpoints,
        )
        write_text(out / "history.csv", buf.getvalue())
        _write_frames(out / "frames.npz", g, body.mesh.facets)
        from softgrasp.io.paraview import write_closing_series

        write_closing_series(out, g, body)
        doc["wall_time_s"] = time.perf_counter() - (self._started if started is None else started)
        self.write_plan_file(out)
        figures.finish()


def _portable_hand(doc: dict[str, Any], folder: Path) -> None:
    """``doc``'s hand file named for its folder (:func:`~softgrasp.io.portable.portable_path`)."""
    from softgrasp.io.portable import portable_path

    params, hand = doc.get("parameters") or {}, doc.get("hand")
    if isinstance(params.get("hand"), str):
        params["hand"] = portable_path(params["hand"], folder)
    if isinstance(hand, dict) and isinstance(hand.get("model"), str):
        hand["model"] = portable_path(hand["model"], folder)


def _write_frames(path: Path, plan: GraspPlan, facets: Any) -> None:
    """The closing increments and the held state, for ``softgrasp view`` (SI units): the frames'
    object, fingertips, forces (normal forces from the history's rows, none at the start) and the
    hand's link polylines (``hand_lines``: where each starts in a frame's ``hand_points``)."""
    import numpy as np

    from softgrasp.io.atomic import atomic_write
    from softgrasp.io.plan_document import hand_polylines

    fr = plan.frames
    assert fr is not None

    def points(lines: list[Any]) -> Any:
        return np.concatenate(lines) if lines else np.zeros((0, 3))

    held_links = hand_polylines(plan)

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as fh:
            np.savez_compressed(
                fh,
                travel=fr.travel,
                positions=fr.positions,
                centres=fr.centres,
                forces=fr.forces,
                held_positions=plan.positions,
                held_centres=plan.centres,
                held_forces=np.array([f.force for f in plan.fingers]),
                facets=np.asarray(facets, dtype=np.int64),
                fingertip_radius=np.float64(plan.config.fingertip_radius),
                finger_names=np.array([f.name for f in plan.fingers]),
                normal_forces=np.vstack([np.zeros((1, len(plan.fingers))), plan.normal_force]),
                held_normal_forces=np.array([f.normal_force for f in plan.fingers]),
                hand_points=np.array([points(hand_polylines(plan, t)) for t in fr.travel]).reshape(
                    len(fr.travel), -1, 3
                ),
                held_hand_points=points(held_links),
                hand_lines=np.cumsum([0, *(len(p) for p in held_links)]).astype(np.int64),
            )

    atomic_write(path, write)


def plan(
    obj: SoftObject | str = "sphere",
    hand: HandModel | str | None = "shadow_like",
    *,
    fingertips: Mapping[str, str] | str | None = None,
    mu: float | None = None,
    fingertip_radius_m: float | None = None,
    step_m: float = 0.0005,
    solver: str = "quasistatic",
    safety_factor: float = 1.25,
    hold_time_s: float = 1.0,
    max_squeeze: float = 0.5,
    refine: int = 12,
    grasp: str | Path | None = None,
    contact_law: str = "resolved",
    max_pressure_Pa: float | None = None,
    max_strain: float | None = None,
    progress: Callable[[float], None] | None = None,
    phase: Callable[[str], None] | None = None,
    keep_rest: bool = True,
) -> Plan:
    """Plan a grasp of ``obj`` (three fingers, or two with a gripper) and its force set-points.

    Parameters
    ----------
    obj:
        The object (:func:`load_object`), or a source for it (built-in name, shape, mesh file in
        metres).
    hand:
        A hand model (:func:`load_hand`: any URDF or MJCF hand with its fingertip mapping),
        ``shadow_like``, ``parallel_jaw``, a URDF or MJCF file, or None / ``none`` for free
        fingertips.
    fingertips:
        A hand file's fingertip links by finger (``{"thumb": "th_tip", ...}`` or
        ``thumb=th_tip,first=ff_tip,middle=mf_tip``); see :func:`load_hand`.
    mu:
        Fingertip friction coefficient; default the object's material file's, else 0.8.
    fingertip_radius_m, step_m:
        Fingertip radius (default: the hand's fingertip spheres'; 8 mm without a hand) and
        closing increment [m].
    solver:
        ``quasistatic`` (a static Newton solve per increment) or ``dynamic`` (explicit
        Runge-Kutta through each increment).
    safety_factor:
        The set-points are this multiple (>= 1) of the least normal forces that hold the object
        under force control in softgrasp's model (the critical scale, ``margin`` in
        ``plan.json``).
    hold_time_s:
        Simulated holding time of the grasp test [s].
    max_squeeze:
        Largest finger travel past first contact, as a fraction of its reach.
    refine:
        The most iterations of the solves for the least squeeze that passes the grasp test and
        that holds, each to a force tolerance of 1 % (a bound: the tolerance ends them first).
    grasp:
        An earlier ``plan.json`` whose initial grasp (contacts, closing lines) is closed from
        instead of searching for one.
    contact_law:
        ``resolved`` (the object's compliance counted once: Hertz's law less what the mesh
        resolves) or ``paper`` (the paper's K delta^n in series with the meshed body).
    max_pressure_Pa, max_strain:
        Limits on the held grasp's peak contact pressure [Pa] and the object's peak principal
        strain; a plan whose least squeeze that holds exceeds one raises ``InfeasibleGrasp``.
    progress:
        Called with the fraction of the plan done (never smaller than the one before).
    phase:
        Called with the name of each phase of the planner as it starts (``initial grasp``,
        ``closing``, ``hold check``, ``set-points``), after every option has been checked.
    keep_rest:
        Keep the object's rest on the table in softgrasp's cache folder, and read it back when
        the same object on the same table is planned again (another hand, other fingertips or
        options): the same plan either way, bit for bit, without settling the object again
        (:mod:`softgrasp.grasp.kept_rest`).
    """
    from softgrasp.grasp.initial import HandLayout
    from softgrasp.grasp.planner import plan_grasp
    from softgrasp.io.options import contact_params, plan_config
    from softgrasp.io.plan_document import plan_document

    started = time.perf_counter()
    if not isinstance(obj, SoftObject):
        obj = load_object(obj)
    hand_name = "none" if hand is None else hand if isinstance(hand, str) else hand.source
    options: dict[str, object] = {
        **PLAN_DEFAULTS,
        "object": obj.source,
        "material": obj.material_spec,
        "mesh_size": obj.mesh_size_m,
        "units": obj.units,
        "reorient": obj.reorient,
        "volume_term": obj.body.volume,
        "fingertip_radius": None if fingertip_radius_m is None else float(fingertip_radius_m),
        "density": obj.density_kg_m3,
        "mass": obj.given_mass_kg,
        "step": float(step_m),
        "solver": solver,
        "safety_factor": float(safety_factor),
        "hold_time": float(hold_time_s),
        "max_squeeze": float(max_squeeze),
        "refine": int(refine),
        "hand": str(hand_name),
        "fingertips": fingertips if fingertips is None or isinstance(fingertips, str)
        else ",".join(f"{k}={v}" for k, v in fingertips.items()),
        "grasp": None if grasp is None else str(grasp),
        "contact_law": contact_law,
        "max_pressure": max_pressure_Pa,
        "max_strain": max_strain,
    }
    if solver not in ("quasistatic", "dynamic"):
        raise ConfigError(f"solver must be quasistatic or dynamic, got {solver!r}")
    if contact_law not in ("resolved", "paper"):
        raise ConfigError(f"contact_law must be resolved or paper, got {contact_law!r}")
    contact = contact_params(obj.material_file, mu, law=contact_law)
    options["mu"] = contact.mu
    if hand is None or isinstance(hand, str):
        config = plan_config(options, contact)
    else:
        r = hand.fingertip_radius(hand.grasp_fingers[0]) if fingertip_radius_m is None else fingertip_radius_m
        config = replace(
            plan_config({**options, "hand": "none", "fingertip_radius": r}, contact),
            hand=hand,
            layout=HandLayout.for_hand(hand),
        )
    g = plan_grasp(obj.body, config, progress=progress, phase=phase, keep_rest=keep_rest)
    doc = plan_document(g, obj.body, obj.name, source_transform=obj.transform, units=obj.units)
    return Plan(obj, g, config, options, doc, _started=started)
