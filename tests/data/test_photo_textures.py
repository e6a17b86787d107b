"""Photographed material textures on synthetic assets: triplanar lookups and the generator option."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from physgm.data.photo_textures import PHOTO_TEXTURES, load_texture, triplanar
from physgm.data.priors import sample_physics
from physgm.data.procedural import make_object
from physgm.physics.materials import MATERIAL_NAMES


def test_every_listed_photograph_loads_and_names_a_material():
    assert set(PHOTO_TEXTURES) <= set(MATERIAL_NAMES)
    for package, relpath in (p for v in PHOTO_TEXTURES.values() for p in v):
        image = load_texture(package, relpath)
        assert image.shape[2] == 3 and 0.0 <= image.min() and image.max() <= 1.0 and image.std() > 0.01


def test_triplanar_reads_the_plane_the_normal_faces():
    tex = np.zeros((4, 4, 3), dtype=np.float32)
    tex[1, 2] = (1.0, 0.0, 0.0)  # row v = 1, column u = 2
    p = np.array([[0.0, 2.5, 1.5], [2.5, 9.0, 1.5], [2.5, 1.5, 7.0]])  # texels per m = 1
    n = np.eye(3)  # +x sees (y, z), +y sees (x, z), +z sees (x, y)
    out = triplanar(tex, p, n, 1.0, np.zeros(3))
    np.testing.assert_allclose(out, [[1, 0, 0]] * 3)


def test_photo_textures_change_the_look_deterministically_and_default_off_keeps_bytes():
    phys = sample_physics("wood", np.random.default_rng(0))

    def colours(**kw):
        return make_object("ellipsoid", phys, 400, np.random.default_rng(7), **kw).gaussians.colors

    plain, again = colours(), colours(photo_textures=0.0)
    assert torch.equal(plain, again)  # the option off draws nothing extra
    photo = colours(photo_textures=1.0, varied_light=True)
    assert torch.equal(photo, colours(photo_textures=1.0, varied_light=True))
    assert (photo - plain).abs().mean() > 0.02
    with pytest.raises(KeyError):
        PHOTO_TEXTURES["jelly"]  # materials without photographs keep their procedural look


def test_a_photographed_texture_carries_the_stiffness_and_poisson_cues():
    """Same asset, photo and light; the stiffest is darker than the softest, as procedural ones are."""
    base = sample_physics("wood", np.random.default_rng(0))

    def colours(stiffness, poisson, seed):
        phys = dataclasses.replace(base, stiffness=stiffness, poisson=poisson)
        obj = make_object("ellipsoid", phys, 600, np.random.default_rng(seed), photo_textures=1.0)
        return obj.gaussians.colors.numpy().astype(np.float64)

    def saturation(c):
        return ((c.max(1) - c.min(1)) / np.maximum(c.max(1), 1e-6)).mean()

    for seed in range(4):
        soft, stiff = colours(0.0, 0.5, seed), colours(1.0, 0.5, seed)
        # tone_factor(1) / tone_factor(0) = 0.82 / 1.12; the texture's scale changes too
        assert 0.6 < stiff.mean() / soft.mean() < 0.85
        assert saturation(colours(0.5, 1.0, seed)) > 1.3 * saturation(colours(0.5, 0.0, seed))
