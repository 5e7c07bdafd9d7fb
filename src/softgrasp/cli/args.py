"""What the commands share: the argument parser's class, number checks, the options naming an
object, progress bars on stderr."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, NoReturn

if TYPE_CHECKING:
    from softgrasp.api.objects import SoftObject
    from softgrasp.io.materialfile import MaterialFile

__all__ = [
    "Parser",
    "positive",
    "number",
    "scheduler",
    "limits",
    "add_common",
    "progress_bar",
    "counting_bar",
    "material_file",
    "load",
    "plan_file",
    "run_folder_of",
]


class Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one clear line."""

    def error(self, message: str) -> NoReturn:  # one clear line instead of usage + error
        self.exit(2, f"softgrasp: error: {message} (see 'softgrasp {self.prog.split()[-1]} --help')\n")


def positive(name: str) -> Callable[[str], float]:
    """An argument type: a number > 0, refused naming the option ``name``."""

    def conv(s: str) -> float:
        try:
            v = float(s)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name} must be a number, got {s!r}") from None
        if not v > 0:
            raise argparse.ArgumentTypeError(f"{name} must be > 0, got {s}")
        return v

    return conv


def number(key: str, flag: str | None = None) -> Callable[[str], float]:
    """An argument type: a number (an integer where the range says so) in the physical range
    ``RANGES[key]`` (:mod:`softgrasp.model.ranges`), refused naming the option ``flag`` (default
    ``--key`` with dashes) before any work."""
    from softgrasp.errors import ConfigError
    from softgrasp.model.ranges import RANGES

    rng = RANGES[key]
    name = flag or "--" + key.replace("_", "-")

    def conv(s: str) -> float:
        try:
            v = int(s) if rng.integer else float(s)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name} must be {rng.expected}, got {s!r}") from None
        try:
            return rng.check(name, v)
        except ConfigError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None

    return conv


def scheduler(text: str) -> str:
    """An argument type: a Dask scheduler's address (``tcp://HOST:PORT``), refused when it does
    not read as one."""
    from softgrasp.errors import ConfigError
    from softgrasp.io.options import scheduler_address

    try:
        return scheduler_address(text)
    except ConfigError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def limits(key: str) -> str:
    """The physical range of option ``key`` for its ``--help`` text: ``in (0, 60] s``."""
    from softgrasp.model.ranges import RANGES

    return RANGES[key].expected.replace("a number ", "").replace("an integer ", "")


def add_common(p: argparse.ArgumentParser) -> None:
    """The options naming the object, its length unit, material and mesh, and the output folder."""
    from softgrasp.model.ranges import VOLUME_TERMS

    p.add_argument(
        "--object",
        default="sphere",
        help="built-in object (cube, sphere), a shape (box:WxDxH, cylinder:DxH, ball:R; in --units) "
        "or a mesh file (.msh .vtk .vtu .stl .obj ..., in --units); 1 mm to 0.5 m across",
    )
    p.add_argument(
        "--units",
        choices=("m", "cm", "mm"),
        default=None,
        help="length unit of the mesh file's coordinates or the shape's sizes (default m)",
    )
    p.add_argument(
        "--material",
        default=None,
        help="preset (foam, rubber), E=..,nu=..,density=.. [Pa, -, kg/m^3] or a material file "
        "(FILE.toml, as calibrate writes; FILE.toml,density=.. to change it); default: the object's "
        "(a mesh file or a shape: rubber's E and nu, with a warning)",
    )
    mass = p.add_mutually_exclusive_group()
    mass.add_argument(
        "--density",
        type=number("density"),
        default=None,
        metavar="KG_M3",
        help=f"the object's density [kg/m^3], {limits('density')}, over its material's (a mesh file "
        "or a shape without one: 1000, with a warning)",
    )
    mass.add_argument(
        "--mass",
        type=number("mass"),
        default=None,
        metavar="KG",
        help=f"the object's total mass [kg], {limits('mass')}, instead of a density; a plan takes "
        "objects of 1 g to 2 kg",
    )
    p.add_argument(
        "--mesh-size",
        type=number("mesh_size"),
        default=None,
        metavar="M",
        help=f"target element size [m], {limits('mesh_size')}, at most half the object's thinnest side",
    )
    p.add_argument(
        "--reorient", action="store_true", help="flip inverted tets of a mesh file instead of refusing it"
    )
    p.add_argument(
        "--volume-term",
        choices=VOLUME_TERMS,
        default=None,
        help="the body's volume term: element (one per tet, the default) or nodal (one per node: "
        "no volumetric locking as nu nears 0.5, about 4x the Newton matrix)",
    )
    p.add_argument(
        "--out",
        default=None,
        metavar="DIR",
        help="output folder; its earlier files of this command are replaced whole at the end",
    )


def progress_bar(desc: str, total: int = 1000):
    """A bar on stderr and its callback taking the fraction done."""
    from tqdm import tqdm

    bar = tqdm(
        total=total,
        desc=desc,
        unit="‰",
        leave=False,
        disable=None,
        file=sys.stderr,
        bar_format="{desc}: {percentage:3.0f}%|{bar}| {elapsed}<{remaining}",
    )

    def update(fraction: float) -> None:
        bar.n = int(round(fraction * total))
        bar.refresh()

    return bar, update


@contextmanager
def counting_bar(
    desc: str, unit: str = " simulations", total: int | None = None
) -> Iterator[Callable[[int], None]]:
    """A bar on stderr counting ``unit``; yields its callback taking the count so far."""
    from tqdm import tqdm

    b = tqdm(total=total, desc=desc, unit=unit, leave=False, disable=None, file=sys.stderr)

    def update(k: int) -> None:
        b.n = k
        b.refresh()

    try:
        yield update
    finally:
        b.close()


def material_file(args: argparse.Namespace) -> MaterialFile | None:
    """The --material FILE.toml of a command, read once (None when --material is not a file)."""
    from softgrasp.io.materialfile import is_material_file, read_material_file

    spec = getattr(args, "material", None)
    if spec is None or not is_material_file(spec):
        return None
    if getattr(args, "_material_file", None) is None:
        args._material_file = read_material_file(spec)
    return args._material_file


def load(args: argparse.Namespace) -> SoftObject:
    """The object of --object, --units, --material, --density, --mass, --mesh-size and --reorient;
    the defaults it takes (:class:`~softgrasp.errors.SoftgraspWarning`) printed on stderr, one line
    each."""
    import warnings

    from softgrasp.api.objects import load_object
    from softgrasp.errors import SoftgraspWarning

    mf = material_file(args)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", SoftgraspWarning)
        obj = load_object(
            args.object,
            units=getattr(args, "units", None) or "m",
            material=mf if mf is not None else args.material,
            mesh_size_m=args.mesh_size,
            reorient=args.reorient,
            density_kg_m3=getattr(args, "density", None),
            mass_kg=getattr(args, "mass", None),
            volume_term=getattr(args, "volume_term", None) or "element",
        )
    for w in caught:
        if issubclass(w.category, SoftgraspWarning):
            print(f"softgrasp: warning: {w.message}", file=sys.stderr)
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    return obj


def plan_file(path: str) -> str:
    """A plan run given as its folder or its ``plan.json``: the ``plan.json``."""
    import os

    return os.path.join(path, "plan.json") if os.path.isdir(path) else path


def run_folder_of(path: str) -> str:
    """A plan run given as its folder or its ``plan.json``: the folder."""
    import os

    return (os.path.dirname(path) or ".") if os.path.isfile(path) else path
