"""Material-conditioned procedural 3D textures and baked shading for synthetic Gaussians.

Every material in the table has a style: a palette that overlaps other materials' palettes
(plastic comes in any colour, wood and leather share browns, paper, snow and ceramic share
whites), a 3D texture evaluated on the surface points, an opacity range (translucent glass and
jelly), a gloss (baked highlight) and, for granular materials, a rough surface and interior
Gaussians. Within a material two visible cues follow the true physics:

* ``stiffness`` (position of E in the material's range): finer texture and darker tone,
  and (in shapes.py) thicker walls for plates and shells;
* ``poisson`` (position of nu in the range): more saturated colour.

Colours are baked with Lambertian + ambient shading under one light from above-front
(towards the azimuth-0 camera), so the renderer's SH-degree-0 colours reproduce the look.
"""

from __future__ import annotations

import colorsys
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

# Light direction (unit, asset frame): above (+z) and in front (+x, the azimuth-0 camera side).
LIGHT_DIR = np.array([0.5, 0.25, 1.0]) / np.linalg.norm([0.5, 0.25, 1.0])
AMBIENT = 0.4  # shade = AMBIENT + (1 - AMBIENT) * max(n.l, 0)


@dataclass
class TextureContext:
    """What a material texture sees for N surface points."""

    p: np.ndarray  # [N, 3] texture coordinates: asset-frame points in the shape's local orientation, m
    n: np.ndarray  # [N, 3] normals in the same orientation
    n_world: np.ndarray  # [N, 3] normals in the asset frame (for environment-like effects)
    stiffness: float  # [0, 1]
    poisson: float  # [0, 1]
    rng: np.random.Generator

    @property
    def freq(self) -> float:
        """Texture frequency multiplier: stiffer assets have finer texture (x0.6 .. x1.6)."""
        return float(2.0 ** (1.4 * (self.stiffness - 0.5)))

    def u(self, lo: float, hi: float) -> float:
        return float(lo + (hi - lo) * self.rng.random())


@dataclass(frozen=True)
class MaterialStyle:
    """How one material looks. The texture returns albedo [N, 3] in [0, 1]."""

    texture: Callable[[TextureContext], np.ndarray]
    # Per-Gaussian opacity; about six discs overlap along a ray through an object (front and
    # back surface), so translucent materials need values far below their look.
    opacity: tuple[float, float] = (0.92, 1.0)
    gloss: tuple[float, float] = (0.0, 0.05)  # strength of the baked highlight
    roughness: float = 0.0  # surface jitter along the normal, in units of Gaussian spacing
    interior: float = 0.0  # fraction of Gaussians placed below the surface
    # Disc size multiplier: translucent materials use wide faint discs, because with narrow
    # faint ones the random density of samples shows through as blotches.
    disc: float = 1.0


# ---------------------------------------------------------------------------------------------
# Noise helpers, vectorised over points.


class ValueNoise:
    """Periodic 3D value noise on a random 32^3 lattice, smooth (quintic) interpolation."""

    def __init__(self, rng: np.random.Generator, size: int = 32):
        self.size = size
        self.table = rng.random((size, size, size))

    def __call__(self, p: np.ndarray) -> np.ndarray:
        """Noise in [0, 1] at points p [N, 3] (lattice units)."""
        i0 = np.floor(p).astype(np.int64)
        f = p - i0
        w = f * f * f * (f * (f * 6 - 15) + 10)
        out = np.zeros(len(p))
        for corner in range(8):
            o = np.array([(corner >> k) & 1 for k in range(3)])
            idx = (i0 + o) % self.size
            wk = np.prod(np.where(o == 1, w, 1 - w), axis=1)
            out += wk * self.table[idx[:, 0], idx[:, 1], idx[:, 2]]
        return out

    def fbm(self, p: np.ndarray, octaves: int = 4) -> np.ndarray:
        """Fractal sum in about [0, 1]: octaves double in frequency and halve in amplitude."""
        total, amp, norm = np.zeros(len(p)), 1.0, 0.0
        for o in range(octaves):
            total += amp * self(p * (2.0**o) + 17.3 * o)
            norm += amp
            amp *= 0.5
        return total / norm


def worley(p: np.ndarray, cells_per_m: float, rng: np.random.Generator) -> np.ndarray:
    """Distance to the nearest random feature point, normalised by the cell size, [N]."""
    lo, hi = p.min(0) - 0.1, p.max(0) + 0.1
    count = int(np.clip(np.prod((hi - lo) * cells_per_m), 8, 20000))
    feats = lo + (hi - lo) * rng.random((count, 3))
    d, _ = cKDTree(feats).query(p)
    return np.clip(d * cells_per_m, 0.0, 1.0)


def hsv(h: float, s: float, v: float) -> np.ndarray:
    return np.array(colorsys.hsv_to_rgb(h % 1.0, float(np.clip(s, 0, 1)), float(np.clip(v, 0, 1))))


def tone_factor(stiffness: float) -> float:
    """The E cue on a colour's HSV value: stiffer assets are darker (x1.12 .. x0.82)."""
    return 1.12 - 0.3 * stiffness


def saturation_factor(poisson: float) -> float:
    """The nu cue on a colour's saturation: x0.55 .. x1.45, 1 on average."""
    return 0.55 + 0.9 * poisson


def base_colour(ctx: TextureContext, h: float, s: float, v: float) -> np.ndarray:
    """Apply the physics cues to a palette colour: saturation from nu, tone from E."""
    return hsv(h, s * saturation_factor(ctx.poisson), v * tone_factor(ctx.stiffness))


def cued_photo(photo: np.ndarray, procedural: np.ndarray, ctx: TextureContext) -> np.ndarray:
    """A photographed albedo [N, 3] that carries the cues the procedural one [N, 3] carries.

    The procedural texture's brightness pattern, relative to its mean, shades the photograph
    (within x0.6 .. x1.4); its mean cannot carry the tone, since that cancels, so the
    photograph's tone and saturation take the factors ``base_colour`` gives a palette colour,
    relative to a mid-range asset's. ``photo_textures.photo_albedo`` scales the photograph with
    ``ctx.freq``, the texture cue.
    """
    pattern = procedural.mean(axis=1, keepdims=True) / max(float(procedural.mean()), 1e-6)
    out = photo * np.clip(pattern, 0.6, 1.4) * (tone_factor(ctx.stiffness) / tone_factor(0.5))
    grey = out.mean(axis=1, keepdims=True)
    return np.clip(grey + (out - grey) * saturation_factor(ctx.poisson), 0.0, 1.0)


def _any_hue(ctx: TextureContext, s: tuple[float, float], v: tuple[float, float]) -> np.ndarray:
    return base_colour(ctx, ctx.rng.random(), ctx.u(*s), ctx.u(*v))


# ---------------------------------------------------------------------------------------------
# Material textures.


def _plastic(ctx):
    col = _any_hue(ctx, (0.45, 0.85), (0.6, 0.95))
    n = ValueNoise(ctx.rng)(ctx.p * 12 * ctx.freq)
    return col * (0.97 + 0.06 * n[:, None])


def _wood(ctx):
    col = base_colour(ctx, ctx.u(0.04, 0.11), ctx.u(0.4, 0.7), ctx.u(0.45, 0.85))
    noise = ValueNoise(ctx.rng)
    axis_off = ctx.rng.normal(size=2) * 0.3  # ring centre off the object axis, as in a cut plank
    r = np.linalg.norm(ctx.p[:, :2] - axis_off, axis=1) + 0.08 * noise.fbm(ctx.p * 4)
    rings = 0.5 + 0.5 * np.sin(2 * np.pi * r * ctx.u(10, 18) * ctx.freq)
    streaks = noise.fbm(ctx.p * np.array([30.0, 30.0, 2.0]) * ctx.freq, 3)
    shade = 0.62 + 0.25 * rings**3 + 0.2 * (streaks - 0.5)
    return col * shade[:, None]


def _metal(ctx):
    h = ctx.rng.choice([ctx.u(0.0, 1.0), ctx.u(0.09, 0.13), ctx.u(0.03, 0.07)])  # steel, gold, copper tints
    s = ctx.u(0.0, 0.08) if ctx.rng.random() < 0.6 else ctx.u(0.3, 0.55)
    col = base_colour(ctx, h, s, ctx.u(0.6, 0.9))
    if ctx.rng.random() < 0.5:  # brushed: fine streaks along one axis
        noise = ValueNoise(ctx.rng)
        streak = noise.fbm(ctx.p * np.array([80.0, 80.0, 1.5]) * ctx.freq, 3)
        return col * (0.85 + 0.3 * (streak - 0.5))[:, None]
    # polished: a fake environment reflection, bright sky above and dark floor below
    sky = np.clip(0.5 + 0.5 * ctx.n_world[:, 2], 0, 1)
    return col * (0.45 + 0.7 * sky**2)[:, None]


def _fabric(ctx):
    col = _any_hue(ctx, (0.25, 0.7), (0.4, 0.85))
    f = ctx.u(14, 24) * ctx.freq
    # Planar projection along the dominant normal axis gives two thread coordinates.
    axis = np.abs(ctx.n).argmax(1)
    a = np.where(axis == 0, ctx.p[:, 1], ctx.p[:, 0]) * f
    b = np.where(axis == 2, ctx.p[:, 1], ctx.p[:, 2]) * f
    over = (np.floor(a) + np.floor(b)) % 2 == 0
    thread = np.where(over, np.abs(np.sin(np.pi * a)), np.abs(np.sin(np.pi * b)))
    out = col * (0.72 + 0.28 * thread)[:, None]
    if ctx.rng.random() < 0.3:  # plaid stripes in a second colour
        stripe = (np.floor(a / 4) % 3 == 0) | (np.floor(b / 4) % 3 == 0)
        out[stripe] = 0.6 * out[stripe] + 0.4 * _any_hue(ctx, (0.3, 0.7), (0.3, 0.8))
    return out


def _stone(ctx):
    col = base_colour(ctx, ctx.u(0.05, 0.12), ctx.u(0.0, 0.25), ctx.u(0.45, 0.8))
    mottle = ValueNoise(ctx.rng).fbm(ctx.p * 6 * ctx.freq)
    speck = ctx.rng.random(len(ctx.p))
    shade = 0.8 + 0.35 * (mottle - 0.5)
    shade = np.where(speck < 0.07, shade * 0.55, np.where(speck > 0.95, shade * 1.2, shade))
    return col * shade[:, None]


def _ceramic(ctx):
    if ctx.rng.random() < 0.5:
        col = base_colour(ctx, ctx.u(0.08, 0.15), ctx.u(0.0, 0.1), ctx.u(0.88, 0.98))
    else:
        col = _any_hue(ctx, (0.3, 0.7), (0.5, 0.9))
    out = np.tile(col, (len(ctx.p), 1))
    if ctx.rng.random() < 0.4:  # painted bands
        z0, width = ctx.u(-0.3, 0.3), ctx.u(0.02, 0.06)
        band = np.abs(ctx.p[:, 2] - z0) < width
        out[band] = _any_hue(ctx, (0.5, 0.9), (0.3, 0.8))
    return out


def _paper(ctx):
    col = base_colour(ctx, ctx.rng.random(), ctx.u(0.0, 0.2), ctx.u(0.86, 0.98))
    fibre = ValueNoise(ctx.rng).fbm(ctx.p * 40 * ctx.freq, 2)
    out = col * (0.97 + 0.06 * fibre)[:, None]
    if ctx.rng.random() < 0.3:  # printed lines
        lines = np.abs(np.sin(np.pi * ctx.p[:, 2] * ctx.u(15, 30))) < 0.12
        out[lines] *= 0.55
    return out


def _leather(ctx):
    if ctx.rng.random() < 0.8:
        col = base_colour(ctx, ctx.u(0.02, 0.1), ctx.u(0.45, 0.8), ctx.u(0.18, 0.65))
    else:
        col = _any_hue(ctx, (0.4, 0.8), (0.3, 0.7))
    grain = worley(ctx.p, 40 * ctx.freq, ctx.rng)
    return col * (0.78 + 0.25 * grain)[:, None]


def _glass(ctx):
    col = base_colour(ctx, ctx.u(0.3, 0.62), ctx.u(0.05, 0.35), ctx.u(0.82, 1.0))
    return np.tile(col, (len(ctx.p), 1))


def _rubber(ctx):
    if ctx.rng.random() < 0.6:
        col = base_colour(ctx, ctx.rng.random(), ctx.u(0.0, 0.15), ctx.u(0.1, 0.32))
    else:
        col = _any_hue(ctx, (0.55, 0.9), (0.4, 0.8))
    n = ValueNoise(ctx.rng)(ctx.p * 25 * ctx.freq)
    return col * (0.95 + 0.1 * n[:, None])


def _foam(ctx):
    col = _any_hue(ctx, (0.1, 0.5), (0.7, 0.95))
    pores = worley(ctx.p, 35 * ctx.freq, ctx.rng)
    return col * np.where(pores < 0.35, 0.68, 1.0)[:, None]


def _snow(ctx):
    col = base_colour(ctx, ctx.u(0.55, 0.62), ctx.u(0.0, 0.12), ctx.u(0.88, 1.0))
    sparkle = ctx.rng.random(len(ctx.p))
    shade = np.where(sparkle > 0.97, 1.1, 0.92 + 0.08 * sparkle)
    return col * shade[:, None]


def _sand(ctx):
    col = base_colour(ctx, ctx.u(0.08, 0.13), ctx.u(0.3, 0.6), ctx.u(0.55, 0.85))
    grain = ctx.rng.random(len(ctx.p))
    return col * (0.82 + 0.3 * grain)[:, None]


def _jelly(ctx):
    col = _any_hue(ctx, (0.6, 0.95), (0.6, 0.95))
    return np.tile(col, (len(ctx.p), 1))


def _plasticine(ctx):
    col = _any_hue(ctx, (0.5, 0.9), (0.45, 0.9))
    noise = ValueNoise(ctx.rng)
    smudge = noise.fbm(ctx.p * 5 * ctx.freq, 3)
    out = col * (0.9 + 0.2 * smudge)[:, None]
    if ctx.rng.random() < 0.4:  # marbled with a second colour
        mix = noise.fbm(ctx.p * 3 * ctx.freq + 5.0, 3) > 0.55
        out[mix] = _any_hue(ctx, (0.5, 0.9), (0.45, 0.9))
    return out


STYLES: dict[str, MaterialStyle] = {
    "plastic": MaterialStyle(_plastic, gloss=(0.0, 0.45)),
    "wood": MaterialStyle(_wood, gloss=(0.0, 0.1)),
    "metal": MaterialStyle(_metal, gloss=(0.3, 0.6)),
    "fabric": MaterialStyle(_fabric, opacity=(0.85, 1.0)),
    "ceramic": MaterialStyle(_ceramic, gloss=(0.3, 0.55)),
    "stone": MaterialStyle(_stone, roughness=0.15),
    "paper": MaterialStyle(_paper),
    "leather": MaterialStyle(_leather, gloss=(0.1, 0.3)),
    "glass": MaterialStyle(_glass, opacity=(0.012, 0.03), gloss=(0.5, 0.7), disc=2.0),
    "rubber": MaterialStyle(_rubber, gloss=(0.0, 0.08)),
    "foam": MaterialStyle(_foam, roughness=0.1),
    "snow": MaterialStyle(_snow, roughness=0.35, interior=0.2),
    "sand": MaterialStyle(_sand, roughness=0.35, interior=0.2),
    "jelly": MaterialStyle(_jelly, opacity=(0.02, 0.045), gloss=(0.3, 0.6), interior=0.35, disc=2.0),
    "plasticine": MaterialStyle(_plasticine, gloss=(0.0, 0.08)),
}


@dataclass(frozen=True)
class Lighting:
    """One light from a direction plus an ambient term that is brighter from the sky than the ground."""

    direction: tuple[float, float, float] = tuple(LIGHT_DIR)  # unit, asset frame, towards the light
    ambient: float = AMBIENT  # ambient share of the shade
    sky: float = 0.0  # ambient x (1 + sky * n_z): 0 is uniform, > 0 lights tops more than undersides

    @staticmethod
    def sample(rng: np.random.Generator) -> Lighting:
        """A light somewhere above the front half (azimuth within 70 degrees of the azimuth-0 camera)."""
        az, el = np.radians(rng.uniform(-70, 70)), np.radians(rng.uniform(25, 75))
        d = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        return Lighting(tuple(d), float(rng.uniform(0.3, 0.5)), float(rng.uniform(0.1, 0.4)))


def shade(albedo: np.ndarray, normals: np.ndarray, gloss: float, light: Lighting = Lighting()) -> np.ndarray:
    """Bake Lambertian + (hemispheric) ambient shading and a view-independent highlight.

    Args:
        albedo: [N, 3] in [0, 1].
        normals: [N, 3] unit, asset frame.
        gloss: highlight strength; the highlight sits where the normal faces the light.
        light: the light; the default is the fixed light real meshes are rendered under.
    Returns:
        colours [N, 3] in [0, 1].
    """
    ndl = np.clip(normals @ np.asarray(light.direction), 0.0, 1.0)
    ambient = light.ambient * (1.0 + light.sky * normals[:, 2]) / (1.0 + light.sky)
    lit = albedo * (ambient + (1 - light.ambient) * ndl)[:, None]
    return np.clip(lit + gloss * ndl[:, None] ** 24, 0.0, 1.0)
