"""Material/contact files: the calibrated parameters that ``--material FILE`` accepts.

A TOML file with an optional ``[material]`` table (``E_Pa``, ``nu``, ``density_kg_m3``, ``name``,
``law = "linear" | "polynomial" | "tabulated"`` with ``a2``, ``a3`` for the polynomial, the arrays
``strain`` and ``stress_Pa`` for the table, e.g. a calibrated edge law) and an optional
``[contact]`` table (``contact_law = "resolved" | "paper"``, ``mu``, ``exponent``,
``stiffness_prefactor``, ``gamma_N_s_m2``, ``damping``). ``softgrasp
calibrate`` writes one; ``plan``, ``indent``, ``compress`` and ``execute`` read it. A ``--material``
value may follow the file's name with ``key=value`` overrides of its material, as after a preset:
``material.toml,density=1000`` (``E``, ``nu``, ``density`` [kg/m^3], ``a2``, ``a3``; ``mass``
[kg] the object's total mass).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

from softgrasp.errors import ConfigError, ContactError, MaterialError
from softgrasp.io.atomic import write_text
from softgrasp.io.tomlfile import read_toml
from softgrasp.model.material import Linear, Material, Polynomial, StressStrainLaw, Tabulated, check_given
from softgrasp.model.ranges import RANGES
from softgrasp.physics.fingertip.params import ContactParams

__all__ = ["MaterialFile", "read_material_file", "write_material_file", "is_material_file"]

#: What ``--material FILE.toml,key=value`` may set.
_OVERRIDES = ("E", "nu", "density", "mass", "a2", "a3")
_MATERIAL_KEYS = {"E_Pa", "nu", "density_kg_m3", "name", "law", "a2", "a3", "strain", "stress_Pa"}
_CONTACT_KEYS = {
    "mu": "mu",
    "exponent": "exponent",
    "stiffness_prefactor": "prefactor",
    "gamma_N_s_m2": "gamma",
    "damping": "damping",
    "contact_law": "law",
}


@dataclass(frozen=True)
class MaterialFile:
    """The contents of a material/contact file.

    Attributes
    ----------
    path: the file.
    material: the material, or None when the file has no ``[material]`` table (with the overrides
        given after the file's name).
    contact: contact parameters given in ``[contact]`` (ContactParams field names), possibly empty.
    mass: the object's total mass [kg] given after the file's name (``,mass=0.1``), or None.
    """

    path: str
    material: Material | None
    contact: dict[str, object]
    mass: float | None = None

    def contact_params(self, base: ContactParams) -> ContactParams:
        """``base`` with this file's contact parameters over it (:meth:`ContactParams.updated`: a
        file that changes the contact law gets that law's defaults for what it does not give)."""
        try:
            return base.updated(**self.contact)
        except (ContactError, TypeError) as exc:
            raise ConfigError(f"material file {self.path}: [contact]: {exc}") from None


def is_material_file(spec: str) -> bool:
    """Whether a ``--material`` value names a file (``.toml``, possibly followed by ``,key=value``
    overrides) rather than a preset or key=value list."""
    return _split_spec(spec)[0].lower().endswith(".toml")


def _split_spec(spec: str) -> tuple[str, str]:
    """A ``--material`` value split into the file's name and the ``key=value`` overrides after it."""
    text = str(spec).strip()
    low = text.lower()
    k = low.find(".toml,")
    if k < 0:
        return text, ""
    return text[: k + 5], text[k + 6 :]


def _with_overrides(mf: MaterialFile, text: str) -> MaterialFile:
    """``mf`` with the ``key=value`` overrides ``text`` over its material, each in its range."""
    import re

    where = f"--material {mf.path},{text}"
    vals: dict[str, float] = {}
    for part in (p.strip() for p in text.split(",") if p.strip()):
        m = re.fullmatch(r"([A-Za-z0-9_]+)\s*=\s*(\S+)", part)
        if not m or m.group(1) not in _OVERRIDES:
            raise ConfigError(
                f"{where}: cannot read {part!r}; after a material file give key=value with the keys "
                f"{', '.join(_OVERRIDES)}"
            )
        key = m.group(1)
        try:
            value = float(m.group(2))
        except ValueError:
            raise ConfigError(f"{where}: {key}={m.group(2)!r} is not a number") from None
        vals[key] = RANGES[key].check(f"{where}: {key}", value, MaterialError)
    mass = vals.pop("mass", None)
    base = mf.material
    if base is None:
        if vals and not {"E", "nu"} <= set(vals):
            raise ConfigError(f"{where}: the file has no [material] table to change; give E and nu too")
        if not vals:
            return replace(mf, mass=mass)
        base = Material(vals["E"], vals["nu"], name="custom")
    law = base.law
    if "a2" in vals or "a3" in vals:
        if isinstance(law, Tabulated):
            raise ConfigError(f"{where}: the file's law is tabulated; a2 and a3 do not apply to it")
        old = law.describe() if isinstance(law, Polynomial) else {"a2": 0.0, "a3": 0.0}
        law = Polynomial(vals.get("a2", float(old["a2"])), vals.get("a3", float(old["a3"])))  # type: ignore[arg-type]
    try:
        E, nu, rho = vals.get("E", base.E), vals.get("nu", base.nu), vals.get("density", base.density)
        mat = check_given(Material(E, nu, rho, law, base.name))
    except MaterialError as exc:
        raise MaterialError(f"{where}: {exc}") from None
    return replace(mf, material=mat, mass=mass)


def _number(path: str, table: str, key: str, value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(float(value)):
        raise ConfigError(f"material file {path}: [{table}] {key} = {value!r} is not a finite number")
    return float(value)


def read_material_file(path: str | Path) -> MaterialFile:
    """Read a material/contact file (module docstring), with the ``key=value`` overrides after its
    name applied. ConfigError says what is wrong and where."""
    name, overrides = _split_spec(str(path))
    mf = _read_file(name)
    return _with_overrides(mf, overrides) if overrides else mf


def _read_file(path: str | Path) -> MaterialFile:
    name = str(path)
    doc = read_toml(path, "material file")
    extra = sorted(set(doc) - {"material", "contact"})
    if extra:
        raise ConfigError(
            f"material file {name}: unknown table(s) {extra}; expected [material] and/or [contact]"
        )
    if not doc:
        raise ConfigError(f"material file {name} is empty; it needs a [material] or [contact] table")
    for table in ("material", "contact"):
        if table in doc and not isinstance(doc[table], dict):
            raise ConfigError(
                f"material file {name}: {table} must be a table ([{table}] with key = value lines), "
                f"got {doc[table]!r}"
            )
    material = None
    m = doc.get("material")
    if m is not None:
        unknown = sorted(set(m) - _MATERIAL_KEYS)
        if unknown:
            raise ConfigError(
                f"material file {name}: unknown [material] key(s) {unknown}; known: {sorted(_MATERIAL_KEYS)}"
            )
        for k in ("E_Pa", "nu"):
            if k not in m:
                raise ConfigError(f"material file {name}: [material] lacks {k}")
        kind = m.get("law", "polynomial" if ("a2" in m or "a3" in m) else "linear")
        law: StressStrainLaw
        if kind != "tabulated" and ("strain" in m or "stress_Pa" in m):
            raise ConfigError(f'material file {name}: strain/stress_Pa need law = "tabulated"')
        if kind == "tabulated":
            for k in ("strain", "stress_Pa"):
                v = m.get(k)
                if not isinstance(v, list):
                    raise ConfigError(f"material file {name}: a tabulated law needs an array {k} = [...]")
            try:
                law = Tabulated(
                    [_number(name, "material", "strain", v) for v in m["strain"]],
                    [_number(name, "material", "stress_Pa", v) for v in m["stress_Pa"]],
                )
            except MaterialError as exc:
                raise MaterialError(f"material file {name}: {exc}") from None
        elif kind == "linear":
            if "a2" in m or "a3" in m:
                raise ConfigError(
                    f'material file {name}: [material] law = "linear" takes no a2/a3; '
                    'use law = "polynomial" or remove them'
                )
            law = Linear()
        elif kind == "polynomial":
            a2, a3 = (
                RANGES[k].check(
                    f"material file {name}: [material] {k}", _number(name, "material", k, m.get(k, 0.0))
                )
                for k in ("a2", "a3")
            )
            law = Polynomial(a2, a3)
        else:
            raise ConfigError(
                f"material file {name}: [material] law must be 'linear', 'polynomial' or 'tabulated', "
                f"got {kind!r}"
            )
        density = m.get("density_kg_m3")
        try:
            material = Material(
                E=_number(name, "material", "E_Pa", m["E_Pa"]),
                nu=_number(name, "material", "nu", m["nu"]),
                density=None if density is None else _number(name, "material", "density_kg_m3", density),
                law=law,
                name=str(m.get("name", Path(name).stem)),
            )
            check_given(material)
        except MaterialError as exc:
            raise MaterialError(f"material file {name}: {exc}") from None
    contact: dict[str, object] = {}
    c = doc.get("contact")
    if c is not None:
        unknown = sorted(set(c) - set(_CONTACT_KEYS))
        if unknown:
            raise ConfigError(
                f"material file {name}: unknown [contact] key(s) {unknown}; known: {sorted(_CONTACT_KEYS)}"
            )
        for k, v in c.items():
            text = k in ("damping", "contact_law")
            contact[_CONTACT_KEYS[k]] = str(v) if text else _number(name, "contact", k, v)
        try:
            ContactParams(**contact)  # type: ignore[arg-type]
        except ContactError as exc:
            raise ConfigError(f"material file {name}: [contact]: {exc}") from None
    return MaterialFile(name, material, contact)


def _toml_value(v: object) -> str:
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    return repr(float(v))  # type: ignore[arg-type]


def write_material_file(
    path: str | Path, material: Material | None, contact: ContactParams | None, *, comment: str = ""
) -> Path:
    """Write a material/contact file atomically (what :func:`read_material_file` reads back)."""
    lines = [f"# {ln}" for ln in comment.splitlines()] if comment else []
    if material is not None:
        law = material.law.describe()
        lines += ["[material]", f"name = {_toml_value(material.name)}"]
        lines += [f"E_Pa = {_toml_value(material.E)}", f"nu = {_toml_value(material.nu)}"]
        if material.density is not None:
            lines.append(f"density_kg_m3 = {_toml_value(material.density)}")
        if law["kind"] == "polynomial":
            lines += [
                'law = "polynomial"',
                f"a2 = {_toml_value(law['a2'])}",
                f"a3 = {_toml_value(law['a3'])}",
            ]
        elif law["kind"] == "linear":
            lines.append('law = "linear"')
        elif law["kind"] == "tabulated":
            lines.append('law = "tabulated"')
            for key in ("strain", "stress_Pa"):
                lines.append(f"{key} = [{', '.join(_toml_value(v) for v in law[key])}]")
        else:
            raise ConfigError(f"a {law['kind']} law cannot be written to a material file")
        lines.append("")
    if contact is not None:
        lines += [
            "[contact]",
            f"contact_law = {_toml_value(contact.law)}",
            f"mu = {_toml_value(contact.mu)}",
            f"exponent = {_toml_value(contact.exponent)}",
            f"stiffness_prefactor = {_toml_value(contact.prefactor)}",
            f"gamma_N_s_m2 = {_toml_value(contact.gamma)}",
            f"damping = {_toml_value(contact.damping)}",
            "",
        ]
    return write_text(path, "\n".join(lines) + "\n")
