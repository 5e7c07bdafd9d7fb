"""Material/contact files: the calibrated parameters that ``--material FILE`` accepts.

A TOML file with an optional ``[material]`` table (``E_Pa``, ``nu``, ``density_kg_m3``, ``name``,
``law = "linear" | "polynomial" | "tabulated"`` with ``a2``, ``a3`` for the polynomial, the arrays
``strain`` and ``stress_Pa`` for the table, e.g. a calibrated edge law) and an optional
``[contact]`` table (``contact_law = "resolved" | "paper"``, ``mu``, ``exponent``,
``stiffness_prefactor``, ``gamma_N_s_m2``, ``damping``). ``softgrasp
calibrate`` writes one; ``plan``, ``indent``, ``compress`` and ``execute`` read it.
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
    material: the material, or None when the file has no ``[material]`` table.
    contact: contact parameters given in ``[contact]`` (ContactParams field names), possibly empty.
    """

    path: str
    material: Material | None
    contact: dict[str, object]

    def contact_params(self, base: ContactParams) -> ContactParams:
        """``base`` with this file's contact parameters over it."""
        try:
            return replace(base, **self.contact)  # type: ignore[arg-type]
        except (ContactError, TypeError) as exc:
            raise ConfigError(f"material file {self.path}: [contact]: {exc}") from None


def is_material_file(spec: str) -> bool:
    """Whether a ``--material`` value names a file (``.toml``) rather than a preset or key=value list."""
    return spec.strip().lower().endswith(".toml")


def _number(path: str, table: str, key: str, value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(float(value)):
        raise ConfigError(f"material file {path}: [{table}] {key} = {value!r} is not a finite number")
    return float(value)


def read_material_file(path: str | Path) -> MaterialFile:
    """Read a material/contact file (module docstring). ConfigError says what is wrong and where."""
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
