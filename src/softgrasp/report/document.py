"""The report's tiny document model and its two renderings (Markdown, self-contained HTML).

A report is a list of blocks: ``("h", level, text)``, ``("p", text)``, ``("ul", [items])``,
``("table", header, rows, align)``, ``("fig", relative path, caption)``, ``("quote", text)``. Text
may hold `code`, **bold** and *italic*. The helpers format numbers, parameter tables and a step's
status and figures as blocks."""

from __future__ import annotations

import base64
import html
import math
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

Block = tuple[Any, ...]


def fmt(x: Any, spec: str = ".4g", scale: float = 1.0, none: str = "–") -> str:
    """``x`` (times ``scale``) formatted with ``spec``; ``none`` for a missing or non-finite value."""
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return none
    return format(float(x) * scale, spec)


def pct(x: Any, spec: str = "+.1f") -> str:
    """A fraction as a percentage with ``spec``; a dash when missing."""
    return "–" if x is None else f"{format(100 * float(x), spec)} %"


def flatten(d: Mapping[str, Any], prefix: str = "") -> list[tuple[str, str]]:
    """Parameter rows ``(dotted.key, value)`` of a nested dict, lists shortened for people."""
    rows: list[tuple[str, str]] = []
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping):
            rows += flatten(v, key + ".")
        elif isinstance(v, list | tuple):
            vals = [
                fmt(x, ".4g") if isinstance(x, int | float) and not isinstance(x, bool) else str(x) for x in v
            ]
            rows.append((key, "[" + ", ".join(vals) + "]"))
        elif isinstance(v, float):
            rows.append((key, fmt(v, ".6g")))
        else:
            rows.append((key, "–" if v is None else str(v)))
    return rows


def params_table(title: str, params: Mapping[str, Any]) -> list[Block]:
    """A bold ``title`` and a table of the flattened ``params``."""
    return [("p", f"**{title}**"), ("table", ["parameter", "value"], flatten(params), "ll")]


def object_rows(obj: Mapping[str, Any]) -> dict[str, Any]:
    """The parameter rows that describe a step's object."""
    m = obj["material"]
    return {
        "object": obj["description"],
        "material": f"{m['name']}: E = {m['E_Pa']:.6g} Pa, nu = {m['nu']:g}, density "
        f"{m['density_kg_m3']:.4g} kg/m^3, law {m['law']['kind']}",
        "mesh": f"mesh size {obj['mesh_size_m'] * 1e3:.3g} mm: {obj['nodes']} nodes, {obj['tets']} tets, "
        f"{obj['facets']} boundary facets",
        "mass_kg": obj["mass_kg"],
        "network": obj["network"],
    }


def status_line(step: Mapping[str, Any]) -> list[Block]:
    """A quote saying that a step failed or was skipped (nothing when it ran)."""
    if step["status"] == "failed":
        return [("quote", f"**FAILED** after {step['wall_time_s']:.1f} s: {step['message']}")]
    if step["status"] == "skipped":
        return [("quote", f"**SKIPPED**: {step['message']}")]
    return []


def figures(step: Mapping[str, Any], captions: Mapping[str, str]) -> list[Block]:
    """The figure blocks of ``step`` with their ``captions`` (those it wrote)."""
    figs = step.get("figures", {})
    return [("fig", figs[k], cap) for k, cap in captions.items() if k in figs]


_INLINE_CODE = re.compile(r"`([^`]+)`")
_BOLD = re.compile(r"\*\*(.+?)\*\*")
_ITALIC = re.compile(r"(?<![\w*])\*([^*\n]+)\*(?![\w*])")


def _inline_html(text: str) -> str:
    """Escape ``text`` for HTML and turn `code`, **bold** and *italic* into tags."""
    parts = _INLINE_CODE.split(text)
    out = []
    for i, part in enumerate(parts):
        if i % 2:
            out.append(f"<code>{html.escape(part)}</code>")
        else:
            s = html.escape(part, quote=False)
            s = _BOLD.sub(r"<strong>\1</strong>", s)
            out.append(_ITALIC.sub(r"<em>\1</em>", s))
    return "".join(out)


def _md_cell(text: str) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def render_markdown(blocks: Sequence[Block]) -> str:
    """The report as Markdown (figures by relative path)."""
    out: list[str] = []
    n_fig = 0
    for b in blocks:
        kind = b[0]
        if kind == "h":
            out.append(f"{'#' * b[1]} {b[2]}")
        elif kind == "p":
            out.append(b[1])
        elif kind == "quote":
            out.append(f"> {b[1]}")
        elif kind == "ul":
            out.append("\n".join(f"- {item}" for item in b[1]))
        elif kind == "table":
            header, rows, align = b[1], b[2], b[3]
            lines = ["| " + " | ".join(_md_cell(h) for h in header) + " |"]
            lines.append("|" + "|".join("---:" if a == "r" else ":---" for a in align) + "|")
            lines += ["| " + " | ".join(_md_cell(c) for c in row) + " |" for row in rows]
            out.append("\n".join(lines))
        elif kind == "fig":
            n_fig += 1
            out.append(f"![Figure {n_fig}]({b[1]})\n\n*Figure {n_fig}. {b[2]}*")
    return "\n\n".join(out) + "\n"


_CSS = """
body{font-family:-apple-system,"Segoe UI",Helvetica,Arial,sans-serif;max-width:60rem;margin:2rem auto;
padding:0 1rem;color:#222;line-height:1.5}
h1{font-size:1.7rem;border-bottom:2px solid #ddd;padding-bottom:.3rem}
h2{font-size:1.35rem;margin-top:2.2rem;border-bottom:1px solid #e4e4e4;padding-bottom:.2rem}
h3{font-size:1.1rem;margin-top:1.6rem}
table{border-collapse:collapse;margin:.6rem 0 1rem;font-size:.9rem}
th,td{border:1px solid #d8d8d8;padding:.25rem .55rem;vertical-align:top}
th{background:#f3f3f3}
td.r,th.r{text-align:right}
code{background:#f4f4f4;padding:0 .2rem;border-radius:3px;font-size:.88em}
blockquote{margin:1rem 0;padding:.5rem 1rem;border-left:4px solid #c9a227;background:#fcf8e8}
figure{margin:1.2rem 0;text-align:center}
figure img{max-width:100%;height:auto;border:1px solid #eee}
figcaption{font-size:.9rem;color:#555;margin-top:.3rem}
"""


def render_html(blocks: Sequence[Block], base: Path) -> str:
    """The report as one self-contained HTML page: CSS inline, each figure read from ``base`` and
    embedded as a base64 PNG data URI (nothing is fetched)."""
    out: list[str] = []
    title = next((b[2] for b in blocks if b[0] == "h" and b[1] == 1), "softgrasp report")
    n_fig = 0
    for b in blocks:
        kind = b[0]
        if kind == "h":
            out.append(f"<h{b[1]}>{_inline_html(b[2])}</h{b[1]}>")
        elif kind == "p":
            out.append(f"<p>{_inline_html(b[1])}</p>")
        elif kind == "quote":
            out.append(f"<blockquote>{_inline_html(b[1])}</blockquote>")
        elif kind == "ul":
            out.append("<ul>" + "".join(f"<li>{_inline_html(i)}</li>" for i in b[1]) + "</ul>")
        elif kind == "table":
            header, rows, align = b[1], b[2], b[3]
            cls = [' class="r"' if a == "r" else "" for a in align]
            head = "".join(f"<th{c}>{_inline_html(str(h))}</th>" for h, c in zip(header, cls, strict=True))
            body = "".join(
                "<tr>"
                + "".join(f"<td{c}>{_inline_html(str(v))}</td>" for v, c in zip(row, cls, strict=True))
                + "</tr>"
                for row in rows
            )
            out.append(f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>")
        elif kind == "fig":
            n_fig += 1
            data = base64.b64encode((base / b[1]).read_bytes()).decode("ascii")
            out.append(
                f'<figure><img alt="Figure {n_fig}" src="data:image/png;base64,{data}">'
                f"<figcaption>Figure {n_fig}. {_inline_html(b[2])}</figcaption></figure>"
            )
    return (
        '<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n'
        f"<title>{html.escape(title)}</title>\n<style>{_CSS}</style>\n</head>\n<body>\n"
        + "\n".join(out)
        + "\n</body>\n</html>\n"
    )
