"""Photographed material textures for synthetic assets, from packages that ship them.

Procedural noise teaches a model nothing about how real wood grain, brushed steel or felt look,
and a frozen ImageNet encoder reads exactly that. robosuite and metaworld ship photographs of
materials as texture images (``scripts/setup.sh`` installs both with ``--no-deps``: only their
files are read, nothing is imported). ``PHOTO_TEXTURES`` lists which image shows which material
of the table; the textures of robosuite's own objects (can, bread, cereal box, lemon, soda) are
left out, because those objects are physgm's real validation set (``physgm.data.real_objects``).

A texture is mapped onto a synthetic surface triplanarly: three planar projections blended by
the normal, so any procedural shape gets it without UV coordinates.
"""

from __future__ import annotations

from functools import cache

import numpy as np
from PIL import Image

from physgm.data.asset_packages import package_root

# material -> (package, path inside the package) of each photograph that shows it
PHOTO_TEXTURES: dict[str, list[tuple[str, str]]] = {
    "wood": [
        ("robosuite", f"models/assets/textures/{n}.png")
        for n in (
            "blue-wood",
            "dark-wood",
            "gray-woodgrain",
            "green-wood",
            "light-wood",
            "red-wood",
            "wood-tiles",
            "wood-varnished-panels",
        )
    ]
    + [
        ("metaworld", f"assets/textures/{n}.png")
        for n in (
            "darkwood",
            "light_wood",
            "light_wood_v2",
            "light_wood_v3",
            "wood",
            "wood1",
            "wood2",
            "wood3",
            "wood4",
            "wood_light",
        )
    ],
    "metal": [
        ("robosuite", f"models/assets/textures/{n}.png")
        for n in ("steel-brushed", "steel-scratched", "metal", "brass-ambra")
    ]
    + [("metaworld", f"assets/textures/{n}.png") for n in ("metal1", "metal2")],
    "ceramic": [
        ("robosuite", "models/assets/textures/ceramic.png"),
        ("robosuite", "models/assets/textures/light-gray-floor-tile.png"),
    ],
    "stone": [
        ("robosuite", f"models/assets/textures/{n}.png")
        for n in ("white-bricks", "gray-plaster", "cream-plaster", "light-gray-plaster", "white-plaster")
    ]
    + [("metaworld", f"assets/textures/{n}.png") for n in ("granite", "marble", "brick1", "plaster1")],
    "fabric": [
        ("robosuite", "models/assets/textures/gray-felt.png"),
        ("metaworld", "assets/scene/textures/fabricPattern.png"),
        ("metaworld", "assets/scene/textures/fabricPlain.png"),
    ],
    "glass": [("robosuite", "models/assets/textures/glass.png")],
    "plasticine": [("robosuite", "models/assets/textures/clay.png")],
    "sand": [("robosuite", "models/assets/textures/dirt.png")],
}
TEXTURE_PX = 256  # photographs are resized to this square size once (about 1 texel per mm on a 20 cm object)


@cache
def load_texture(package: str, relpath: str) -> np.ndarray:  # [TEXTURE_PX, TEXTURE_PX, 3] float32 in [0, 1]
    root = package_root(package, "photo textures are read from it (or generate with --photo-textures 0)")
    path = root / relpath
    if not path.is_file():
        raise FileNotFoundError(f"texture {relpath} is missing from the installed package {package} ({path})")
    with Image.open(path) as im:
        im = im.convert("RGB").resize((TEXTURE_PX, TEXTURE_PX), Image.Resampling.LANCZOS)
        return np.asarray(im, dtype=np.float32) / 255.0


def has_photos(material: str) -> bool:
    return material in PHOTO_TEXTURES


def triplanar(
    image: np.ndarray,  # [S, S, 3] texture
    p: np.ndarray,  # [N, 3] surface points, m
    n: np.ndarray,  # [N, 3] unit normals in the same frame
    texels_per_m: float,
    offset: np.ndarray,  # [3] random shift of the texture, m
) -> np.ndarray:  # [N, 3] albedo
    """Sample a tiling texture by three planar projections blended by the normal (sharpness 4)."""
    s = image.shape[0]
    q = (p + offset) * texels_per_m
    w = np.abs(n) ** 4
    w /= w.sum(axis=1, keepdims=True) + 1e-12
    out = np.zeros((len(p), 3), dtype=np.float64)
    for axis, (a, b) in enumerate(((1, 2), (0, 2), (0, 1))):
        u = np.floor(q[:, a]).astype(np.int64) % s
        v = np.floor(q[:, b]).astype(np.int64) % s
        out += w[:, axis : axis + 1] * image[v, u]
    return out


def photo_albedo(
    material: str, p: np.ndarray, n: np.ndarray, rng: np.random.Generator, freq: float = 1.0
) -> np.ndarray:  # [N, 3]
    """A randomly chosen photograph of ``material`` on the surface, at a random scale and offset.

    ``freq`` multiplies the texture's frequency (the stiffness cue, ``TextureContext.freq``).
    """
    choices = PHOTO_TEXTURES[material]
    package, relpath = choices[int(rng.integers(len(choices)))]
    image = load_texture(package, relpath)
    texels_per_m = freq * TEXTURE_PX / rng.uniform(0.15, 0.5)  # one tile spans 15-50 cm at freq 1
    return triplanar(image, p, n, texels_per_m, rng.uniform(0, 1, size=3))
