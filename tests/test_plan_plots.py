"""Figures of the grasp planner: force curves and the 3D grasp picture (synthetic data)."""

from __future__ import annotations

import time

import numpy as np
import pytest

pytest.importorskip("matplotlib")

from softgrasp.model.objects import make_object  # noqa: E402
from softgrasp.viz.plots import (  # noqa: E402
    plot_grasp_3d,
    plot_plan_force_penetration,
    plot_plan_forces,
)

NAMES = ["thumb", "first", "middle"]


@pytest.fixture(scope="module")
def grasp():
    """Rubber sphere with three fingertips on its equator, 120 deg apart, pushing inward."""
    mesh, _, mass = make_object("sphere", 0.02)
    centre = mesh.centroid
    radius = 0.5 * float(np.ptp(mesh.points[:, 0]))
    r_tip = 0.01
    ang = np.deg2rad([0.0, 120.0, 240.0])
    out = np.stack([np.cos(ang), np.sin(ang), np.zeros(3)], axis=1)
    contacts = centre + radius * out
    return {
        "points": np.array(mesh.points),
        "facets": np.array(mesh.facets),
        "centres": contacts + r_tip * out,
        "radii": np.full(3, r_tip),
        "forces": -np.array([2.0, 1.1, 0.9])[:, None] * out,
        "contact_points": contacts,
        "names": NAMES,
        "weight": (np.array(centre), 9.81 * mass),
    }


def _check_png(path, min_side: int = 300):
    import matplotlib.image as mpimg

    assert path.is_file() and path.stat().st_size > 5_000
    img = mpimg.imread(path)
    assert img.ndim == 3 and img.shape[2] in (3, 4)
    assert min(img.shape[:2]) >= min_side and max(img.shape[:2]) < 4000
    rgb = img[..., :3].reshape(-1, 3)
    assert np.ptp(rgb, axis=0).max() > 0.5, "image is (nearly) a single colour"
    return img


def _curves(K: int = 8):
    inc = np.arange(K, dtype=float)
    norms = np.outer(np.linspace(0.0, 1.0, K) ** 1.5, [2.0, 1.1, 0.9])
    pens = np.outer(np.linspace(0.0, 1.0, K), [6e-3, 4.5e-3, 4e-3])
    return inc, norms, pens


def test_plot_plan_forces_writes_png(tmp_path):
    inc, norms, _ = _curves()
    out = plot_plan_forces(inc, norms, NAMES, tmp_path / "forces.png")
    assert out == tmp_path / "forces.png"
    _check_png(out)


def test_plot_plan_forces_draws_the_held_set_points_and_checks_them(tmp_path):
    """The held state's set-points are drawn after the closing (the closing ends on the table,
    so its last forces are not the set-points): a different picture, and a wrong count or a NaN
    is refused before anything is written."""
    inc, norms, _ = _curves()
    plain = plot_plan_forces(inc, norms, NAMES, tmp_path / "plain.png").read_bytes()
    held = plot_plan_forces(inc, norms, NAMES, tmp_path / "held.png", setpoints=[2.4, 1.2, 1.0])
    _check_png(held)
    assert held.read_bytes() != plain
    for bad, match in (([1.0, 2.0], r"setpoints must have shape \(3,\)"), ([1.0, np.nan, 1.0], "NaN")):
        with pytest.raises(ValueError, match=match):
            plot_plan_forces(inc, norms, NAMES, tmp_path / "bad.png", setpoints=bad)
        assert not (tmp_path / "bad.png").exists()


def test_plot_plan_force_penetration_writes_png(tmp_path):
    _, norms, pens = _curves()
    out = plot_plan_force_penetration(pens, norms, NAMES, tmp_path / "fp.png")
    _check_png(out)


@pytest.mark.parametrize(
    "args, match",
    [
        ((np.arange(5), np.zeros((4, 3)), NAMES), r"force_norms must have shape \(5, n\)"),
        ((np.zeros((5, 1)), np.zeros((5, 3)), NAMES), r"increments must have shape \(n,\)"),
        ((np.arange(5), np.zeros((5, 3)), NAMES[:2]), "names has 2 entries but the data has 3 fingers"),
        ((np.arange(5), np.full((5, 3), np.nan), NAMES), "force_norms holds NaN"),
    ],
)
def test_plot_plan_forces_rejects_bad_input(tmp_path, args, match):
    with pytest.raises(ValueError, match=match):
        plot_plan_forces(*args, tmp_path / "bad.png")
    assert not (tmp_path / "bad.png").exists()


def test_plot_plan_force_penetration_rejects_bad_shapes(tmp_path):
    with pytest.raises(ValueError, match=r"force_norms must have shape \(5, 3\), got \(5, 2\)"):
        plot_plan_force_penetration(np.zeros((5, 3)), np.zeros((5, 2)), NAMES, tmp_path / "bad.png")
    with pytest.raises(ValueError, match=r"penetrations must have shape \(n, n\)"):
        plot_plan_force_penetration(np.zeros(5), np.zeros(5), NAMES, tmp_path / "bad.png")


def test_plot_grasp_3d_writes_png_quickly(tmp_path, grasp):
    t0 = time.perf_counter()
    out = plot_grasp_3d(**grasp, path=tmp_path / "grasp.png", title="synthetic grasp")
    elapsed = time.perf_counter() - t0
    img = _check_png(out, min_side=400)
    # The three finger colours (tab:red, tab:blue, tab:green) appear in the picture.
    rgb = img[..., :3].reshape(-1, 3)
    for colour in ((0.84, 0.15, 0.16), (0.12, 0.47, 0.71), (0.17, 0.63, 0.17)):
        near = np.abs(rgb - np.array(colour)).max(axis=1) < 0.12
        assert near.sum() > 50, f"colour {colour} missing"
    assert elapsed < 10.0  # ~0.3 s here; generous for a loaded CI machine


def test_plot_grasp_3d_names_the_set_points_beside_the_forces(tmp_path, grasp):
    """The legend gives each finger's |force| in the picture and, when given, its set-point (a
    held state's forces are not the set-points): a different picture."""
    plain = plot_grasp_3d(**grasp, path=tmp_path / "plain.png").read_bytes()
    named = plot_grasp_3d(**grasp, path=tmp_path / "named.png", setpoints=[0.363, 0.237, 0.245])
    _check_png(named, min_side=400)
    assert named.read_bytes() != plain


def test_plot_grasp_3d_without_weight_title_or_forces(tmp_path, grasp):
    args = dict(grasp, weight=None, forces=np.zeros((3, 3)))
    _check_png(plot_grasp_3d(**args, path=tmp_path / "g.png"))


@pytest.mark.parametrize(
    "change, match",
    [
        ({"points": np.zeros((10, 2))}, r"points must have shape \(n, 3\), got \(10, 2\)"),
        ({"facets": np.zeros((4, 4), dtype=int)}, r"facets must have shape \(F, 3\)"),
        ({"facets": np.array([[0, 1, 10**6]])}, "facets refer to node indices outside"),
        ({"facets": np.array([[0.0, 1.0, 2.0]])}, "facets must hold integer node indices"),
        ({"centres": np.zeros((3, 2))}, r"centres must have shape \(n, 3\)"),
        ({"radii": np.full(2, 0.01)}, r"radii must have shape \(3,\), got \(2,\)"),
        ({"radii": np.array([0.01, 0.0, 0.01])}, "radii must be > 0"),
        ({"forces": np.zeros((2, 3))}, r"forces must have shape \(3, 3\), got \(2, 3\)"),
        ({"contact_points": np.zeros(3)}, r"contact_points must have shape \(3, 3\)"),
        ({"names": ["thumb"]}, "names has 1 entries but the data has 3 fingers"),
        ({"weight": (np.zeros(2), 0.5)}, r"weight centre of mass must have shape \(3,\)"),
        ({"weight": (np.zeros(3), -1.0)}, "weight must be a finite force >= 0 N"),
        ({"setpoints": [0.3, 0.2]}, r"setpoints must have shape \(3,\), got \(2,\)"),
        ({"setpoints": [0.3, np.nan, 0.2]}, "setpoints holds NaN"),
    ],
)
def test_plot_grasp_3d_rejects_bad_input(tmp_path, grasp, change, match):
    with pytest.raises(ValueError, match=match):
        plot_grasp_3d(**dict(grasp, **change), path=tmp_path / "bad.png")
    assert not (tmp_path / "bad.png").exists()
