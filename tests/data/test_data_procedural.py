"""Procedural shapes, surface sampling, material styles and physics cues."""

from __future__ import annotations

import colorsys
import math

import numpy as np
import pytest
import torch
import trimesh

from physgm.data.appearance import STYLES
from physgm.data.priors import material_names, sample_physics
from physgm.data.procedural import make_object, tangent_frames
from physgm.data.shapes import FAMILIES, OBJECT_RADIUS, Part, make_shape, sample_surface
from physgm.data.synth import render_rgba, view_cameras
from physgm.gaussians import quat_to_rotmat
from physgm.physics.materials import get_material


def test_at_least_ten_families_and_every_material_styled():
    assert len(FAMILIES) >= 10
    assert set(STYLES) == set(material_names())


@pytest.mark.parametrize("family", list(FAMILIES))
def test_shape_is_normalised_to_asset_frame(family):
    shape = make_shape(family, np.random.default_rng(1), stiffness=0.5)
    v = np.concatenate([p.mesh.vertices for p in shape.parts])
    assert np.linalg.norm(v, axis=1).max() == pytest.approx(OBJECT_RADIUS, rel=1e-9)
    np.testing.assert_allclose((v.min(0) + v.max(0)) / 2, 0.0, atol=1e-9)  # bbox centred
    s = sample_surface(shape.parts, 500, np.random.default_rng(2))
    np.testing.assert_allclose(np.linalg.norm(s.normals, axis=1), 1.0, atol=1e-9)
    assert s.area > 0 and np.isfinite(s.points).all()


def test_ellipsoid_samples_have_outward_normals():
    shape = make_shape("ellipsoid", np.random.default_rng(0))
    part = shape.parts[0]
    s = sample_surface([part], 4000, np.random.default_rng(0))
    # Outward: normals point away from the centre of this convex shape.
    assert (np.einsum("nd,nd->n", s.normals, s.points) > 0).all()
    assert s.area == pytest.approx(part.mesh.area)


def test_stratified_sampling_counts_per_face():
    mesh = trimesh.creation.box(extents=[1.0, 2.0, 3.0])
    n = 2200
    s = sample_surface([Part(mesh, False)], n, np.random.default_rng(5))
    # Count samples per axis-aligned box side through the face normals.
    for axis, area in [(0, 2 * 6.0), (1, 2 * 3.0), (2, 2 * 2.0)]:
        count = int((np.abs(s.normals[:, axis]) > 0.99).sum())
        assert abs(count - n * area / mesh.area) <= 2  # Poisson sampling would be off by ~30


def test_tangent_frames_are_rotations_with_normal_last():
    n = np.random.default_rng(0).normal(size=(100, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    R = tangent_frames(n)
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    np.testing.assert_allclose(R[:, :, 2], n, atol=1e-12)


def test_gaussians_are_flat_discs_along_the_normal():
    phys = sample_physics("plastic", np.random.default_rng(0))
    g = make_object("ellipsoid", phys, 2000, np.random.default_rng(0)).gaussians
    normal_axis = quat_to_rotmat(g.quats)[:, :, 2]
    # Scales: two equal tangent axes and a thin third one (along the surface normal).
    assert torch.allclose(g.scales[:, 0], g.scales[:, 1])
    assert (g.scales[:, 2] < 0.3 * g.scales[:, 0]).all()
    assert ((normal_axis * g.means).sum(1) > 0).float().mean() > 0.99
    assert g.opacities.min() > 0.8 and g.colors.min() >= 0 and g.colors.max() <= 1


def test_physics_samples_stay_in_table_ranges_and_are_log_uniform():
    rng = np.random.default_rng(0)
    for name in material_names():
        spec = get_material(name)
        draws = [sample_physics(name, rng) for _ in range(200)]
        E = np.array([d.E for d in draws])
        nu = np.array([d.nu for d in draws])
        assert (E >= spec.E_range[0] * 0.999999).all() and (E <= spec.E_range[1] * 1.000001).all()
        assert (nu >= spec.nu_range[0] - 1e-12).all() and (nu <= spec.nu_range[1] + 1e-12).all()
        mid = (math.log10(spec.E_range[0]) + math.log10(spec.E_range[1])) / 2
        half = (math.log10(spec.E_range[1]) - math.log10(spec.E_range[0])) / 2
        assert abs(np.log10(E).mean() - mid) < 0.2 * half + 1e-9  # log-uniform mean is the log-middle
        assert all(d.density > 0 for d in draws)


def _render(material, family, stiffness, poisson, seed, res=32, n=800):
    phys = sample_physics(material, np.random.default_rng(seed))
    phys = type(phys)(phys.material, phys.E, phys.nu, phys.density, stiffness, poisson)
    obj = make_object(family, phys, n, np.random.default_rng(seed))
    cams, _, _ = view_cameras(res)
    return render_rgba(obj.gaussians, cams[[0, 10, 20]], "warp").astype(np.float64) / 255, obj


def _stats(rgba):
    a = rgba[..., 3]
    m = a > 0.5
    rgb = rgba[..., :3][m]
    hsv = np.array([colorsys.rgb_to_hsv(*c) for c in rgb[::3]])
    inside = a > 0.02
    return {
        "alpha": a[inside].mean(),
        "value": hsv[:, 2].mean(),
        "sat": hsv[:, 1].mean(),
        "texture": rgb.std(0).mean(),
    }


def test_every_material_renders_with_distinct_statistics():
    stats = {}
    for name in material_names():
        rgba, _ = _render(name, "ellipsoid", 0.5, 0.5, seed=0)  # same shape for every material
        assert rgba[..., 3].max() > 0.1, f"{name} renders empty"
        stats[name] = _stats(rgba)
    vec = {k: np.array(list(v.values())) for k, v in stats.items()}
    names = list(vec)
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            assert np.abs(vec[a] - vec[b]).max() > 1e-3, f"{a} and {b} look identical"
    # Looks that define the materials: translucent glass and jelly, bright unsaturated snow.
    opaque = [stats[m]["alpha"] for m in ("plastic", "wood", "stone", "metal", "rubber", "paper")]
    assert max(stats["glass"]["alpha"], stats["jelly"]["alpha"]) < 0.75 * min(opaque)
    assert stats["snow"]["value"] > stats["stone"]["value"] + 0.1 and stats["snow"]["sat"] < 0.05
    assert stats["metal"]["sat"] < 0.1 < stats["plastic"]["sat"]


def test_cues_follow_physics_within_a_material():
    """Saturation rises with nu, tone darkens with E, plates and shells thicken with E."""
    sat, val = [], []
    for seed in range(6):
        lo, _ = _render("plastic", "ellipsoid", 0.5, 0.0, seed)
        hi, _ = _render("plastic", "ellipsoid", 0.5, 1.0, seed)
        sat.append(_stats(hi)["sat"] - _stats(lo)["sat"])
        soft, _ = _render("plastic", "ellipsoid", 0.0, 0.5, seed)
        stiff, _ = _render("plastic", "ellipsoid", 1.0, 0.5, seed)
        val.append(_stats(soft)["value"] - _stats(stiff)["value"])
    assert min(sat) > 0 and min(val) > 0
    for family in ("plate", "shell"):
        thin = make_shape(family, np.random.default_rng(4), stiffness=0.0)
        thick = make_shape(family, np.random.default_rng(4), stiffness=1.0)
        assert thick.thickness > 1.5 * thin.thickness
