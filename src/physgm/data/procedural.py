"""Synthetic objects as 3D Gaussians: a procedural shape, a material style, baked shading.

Surface points become small flat Gaussians (disc-shaped, thin along the normal); granular
and translucent materials add Gaussians below the surface. The result is exactly what the
model's Gaussians can represent, so the target appearance has no representation gap.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from physgm.data.appearance import STYLES, Lighting, TextureContext, cued_photo, shade
from physgm.data.photo_textures import has_photos, photo_albedo
from physgm.data.priors import TruePhysics
from physgm.data.shapes import Shape, make_shape, sample_surface
from physgm.gaussians import Gaussians, rotmat_to_quat

# Disc radius (std) relative to the mean spacing of surface samples: large enough that the
# back surface never shows through gaps between discs, small enough to keep texture detail.
TANGENT_SCALE = 0.85
FLATNESS = 0.2  # normal std / tangential std for opaque surfaces


@dataclass
class SyntheticObject:
    """A generated object: its Gaussians and how it was made."""

    gaussians: Gaussians
    shape: Shape
    gloss: float


def tangent_frames(normals: np.ndarray) -> np.ndarray:
    """Right-handed frames [N, 3, 3] whose third column is the normal [N, 3]."""
    helper = np.where(np.abs(normals[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = np.cross(helper, normals)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(normals, t1)
    return np.stack([t1, t2, normals], axis=-1)


def make_object(
    family: str,
    physics: TruePhysics,
    count: int,
    rng: np.random.Generator,
    photo_textures: float = 0.0,
    varied_light: bool = False,
) -> SyntheticObject:
    """Build the Gaussians of one synthetic asset.

    Args:
        family: shape family name (``physgm.data.shapes.FAMILIES``).
        physics: true physics; its material picks the style, its cues modulate shape and texture.
        count: number of Gaussians N.
        rng: the asset's generator (the only source of randomness).
        photo_textures: chance that a material with photographs (``physgm.data.photo_textures``)
            wears one instead of its procedural texture, with the same cues (``appearance.cued_photo``).
        varied_light: a random light above the front half and a sky-brighter ambient, instead
            of the one fixed light.
    """
    if physics.material not in STYLES:
        raise KeyError(
            f"no appearance style for material {physics.material!r}; add one to STYLES in "
            "physgm.data.appearance"
        )
    if count < 16:
        raise ValueError(f"count must be at least 16 Gaussians, got {count}")
    style = STYLES[physics.material]
    rng_shape, rng_points, rng_tex, rng_gauss = rng.spawn(4)
    shape = make_shape(family, rng_shape, physics.stiffness)

    n_int = int(round(count * style.interior))
    n_surf = count - n_int
    surf = sample_surface(shape.parts, n_surf, rng_points)
    spacing = float(np.sqrt(surf.area / n_surf))
    pts, nrm = surf.points, surf.normals
    if style.roughness > 0:  # granular surfaces: grains stick out and sink in
        pts = pts + nrm * (rng_points.normal(size=(n_surf, 1)) * style.roughness * spacing)
    if n_int:
        src = rng_points.integers(n_surf, size=n_int)
        depth = rng_points.random(n_int) * min(shape.thickness, 0.12)
        pts = np.concatenate([pts, pts[src] - nrm[src] * depth[:, None]])
        nrm = np.concatenate([nrm, nrm[src]])

    ctx = TextureContext(
        p=shape.texture_coords(pts),
        n=nrm @ shape.rotation,
        n_world=nrm,
        stiffness=physics.stiffness,
        poisson=physics.poisson,
        rng=rng_tex,
    )
    albedo = np.clip(style.texture(ctx), 0.0, 1.0)
    # Drawn from a stream of their own, so assets made without these options keep their bytes.
    rng_look = rng.spawn(1)[0] if photo_textures or varied_light else None
    if photo_textures and has_photos(physics.material) and rng_look.random() < photo_textures:
        albedo = cued_photo(photo_albedo(physics.material, ctx.p, ctx.n, rng_look, ctx.freq), albedo, ctx)
    gloss = float(style.gloss[0] + (style.gloss[1] - style.gloss[0]) * rng_gauss.random())
    colors = shade(albedo, nrm, gloss, Lighting.sample(rng_look) if varied_light else Lighting())

    base_opacity = style.opacity[0] + (style.opacity[1] - style.opacity[0]) * rng_gauss.random()
    opac = np.clip(base_opacity * (1 + 0.04 * rng_gauss.normal(size=count)), 0.01, 1.0)
    flat = FLATNESS if style.roughness < 0.3 else 0.6  # grains are rounder than painted surfaces
    s_t = TANGENT_SCALE * style.disc * spacing
    scales = np.tile([s_t, s_t, flat * s_t], (count, 1)) * rng_gauss.uniform(0.85, 1.15, size=(count, 1))
    quats = rotmat_to_quat(torch.from_numpy(tangent_frames(nrm)))

    g = Gaussians(
        means=torch.from_numpy(pts).float(),
        quats=quats.float(),
        scales=torch.from_numpy(scales).float(),
        opacities=torch.from_numpy(opac).float(),
        colors=torch.from_numpy(colors).float(),
    )
    return SyntheticObject(g, shape, gloss)
