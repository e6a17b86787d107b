"""Regenerate the example inputs: ``python examples/make_examples.py [--out examples]``.

Every example is procedural (synthetic PhysAssets objects, ``physgm.data.synth``), so nothing
here comes from a photo collection:

* ``jelly_cube.png``, ``metal_can.png``: the canonical view (elevation 0, azimuth 0) as RGBA,
  256 px: the mask comes from alpha.
* ``rubber_blob_plain.jpg``: the object composited into a 320 x 240 "studio photo" (plain
  light background, soft contact shadow, sensor noise), no alpha: plain-background segmentation.
* ``wood_toy_cluttered.jpg``: the same idea over a cluttered table scene: GrabCut segmentation.
* ``plasticine_views/``: 4 posed RGBA views (azimuth 0, 90, 180, 270) at 128 px + cameras.json.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np
from PIL import Image, ImageFilter

from physgm.data.synth import SynthConfig, generate_asset

# name -> (material, shape family, seed)
OBJECTS = {
    "jelly_cube": ("jelly", "rounded_box", 4),
    "metal_can": ("metal", "cylinder", 2),
    "rubber_blob": ("rubber", "blob", 1),
    "wood_toy": ("wood", "composite", 5),
    "plasticine": ("plasticine", "capsule", 3),
}


def make_asset(name: str, resolution: int, tmp: Path) -> Path:
    material, family, seed = OBJECTS[name]
    cfg = SynthConfig(count=1, seed=seed, resolution=resolution, gaussians=8000, video_fraction=0.0,
                      materials=[material], families=[family])  # fmt: skip
    generate_asset(cfg, 0, tmp / name)
    return next((tmp / name).iterdir())


def rgba(asset: Path, view: int) -> np.ndarray:
    return (
        np.asarray(Image.open(asset / "rgba" / f"{view:03d}.png").convert("RGBA")).astype(np.float32) / 255.0
    )


def composite(obj: np.ndarray, background: np.ndarray, at: tuple[int, int], shadow: float, rng) -> np.ndarray:
    """Object RGBA [h, w, 4] over background [H, W, 3], top-left corner at ``at``, with a contact shadow."""
    out = background.copy()
    h, w = obj.shape[:2]
    y0, x0 = at
    ys, xs = np.nonzero(obj[..., 3] > 0.5)
    bottom, cx, half = y0 + ys.max(), x0 + (xs.min() + xs.max()) / 2, (xs.max() - xs.min()) / 2
    yy, xx = np.mgrid[: out.shape[0], : out.shape[1]]
    blob = np.exp(-(((xx - cx) / (0.9 * half)) ** 2 + ((yy - bottom) / (0.12 * half)) ** 2))
    out *= 1 - shadow * blob[..., None]
    a = obj[..., 3:]
    out[y0 : y0 + h, x0 : x0 + w] = obj[..., :3] * a + out[y0 : y0 + h, x0 : x0 + w] * (1 - a)
    return np.clip(out + rng.normal(0, 0.006, out.shape), 0, 1)


def cluttered_background(h: int, w: int, rng) -> np.ndarray:
    """A table top and wall with scattered shapes of muted colours, slightly blurred."""
    yy = np.linspace(0, 1, h)[:, None, None]
    img = np.where(
        yy < 0.45, np.array([0.70, 0.68, 0.62]), np.array([0.55, 0.42, 0.30]) * (0.9 + 0.2 * yy)
    ) * np.ones((h, w, 3))
    pil = Image.fromarray((img * 255).astype(np.uint8))
    from PIL import ImageDraw

    draw = ImageDraw.Draw(pil)
    for _ in range(40):
        x, y = rng.integers(0, w), rng.integers(0, h)
        r = rng.integers(6, 28)
        colour = tuple(int(c) for c in rng.integers(40, 220, 3))
        if rng.random() < 0.5:
            draw.ellipse((x - r, y - r, x + r, y + r // 2), fill=colour)
        else:
            draw.rectangle((x - r, y - r // 2, x + r, y + r), fill=colour)
    return np.asarray(pil.filter(ImageFilter.GaussianBlur(1.2))).astype(np.float32) / 255.0


def save_jpeg(path: Path, img: np.ndarray) -> None:
    Image.fromarray(np.round(img * 255).astype(np.uint8)).save(path, quality=88)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent)
    args = parser.parse_args(argv)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for name in ("jelly_cube", "metal_can"):
            Image.fromarray(np.round(rgba(make_asset(name, 256, tmp), 0) * 255).astype(np.uint8)).save(
                out / f"{name}.png", optimize=True
            )
        blob = rgba(make_asset("rubber_blob", 176, tmp), 0)
        plain = np.full((240, 320, 3), 0.93, np.float32)
        save_jpeg(out / "rubber_blob_plain.jpg", composite(blob, plain, (36, 72), 0.06, rng))
        toy = rgba(make_asset("wood_toy", 208, tmp), 0)
        save_jpeg(
            out / "wood_toy_cluttered.jpg",
            composite(toy, cluttered_background(256, 320, rng), (30, 56), 0.35, rng),
        )
        asset = make_asset("plasticine", 128, tmp)
        views = out / "plasticine_views"
        (views / "rgba").mkdir(parents=True, exist_ok=True)
        cams = json.loads((asset / "cameras.json").read_text())
        frames = []
        for view in (0, 2, 4, 6):  # azimuth 0, 90, 180, 270 at elevation 0
            Image.open(asset / "rgba" / f"{view:03d}.png").save(
                views / "rgba" / f"{view:03d}.png", optimize=True
            )
            frames.append(cams["frames"][view])
        (views / "cameras.json").write_text(json.dumps({**cams, "frames": frames}, indent=1) + "\n")
    for path in sorted(out.rglob("*")):
        if path.is_file() and path.suffix != ".py":
            print(f"{path.relative_to(out)}: {path.stat().st_size / 1024:.0f} KB")


if __name__ == "__main__":
    main()
