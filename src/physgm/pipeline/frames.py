"""Rendering a simulated trajectory into frames over a (floor) background, with a progress bar."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import torch

from physgm.cameras import Cameras
from physgm.gaussians import Gaussians, write_ply
from physgm.render import Renderer


def finite_gaussians(g: Gaussians) -> bool:
    return all(bool(torch.isfinite(t).all()) for t in (g.means, g.quats, g.scales, g.opacities, g.colors))


def render_gaussians(
    g: Gaussians,
    camera: Cameras,
    renderer: Renderer,
    background: np.ndarray,  # [H, W, 3] float in [0, 1]
    device: str,
) -> np.ndarray:  # [H, W, 3] float
    """One image of ``g`` composited over a per-pixel background."""
    g = g.to(device)
    cam = camera.to(device)
    with torch.no_grad():
        rgb, alpha, _ = renderer(
            g.means, g.quats, g.scales, g.opacities, g.colors, cam.viewmats, cam.Ks, cam.width, cam.height
        )
    rgb, alpha = rgb[0].cpu().numpy(), alpha[0].cpu().numpy()
    return rgb + (1.0 - alpha) * background  # the renderer's rgb has no background (premultiplied)


def render_trajectory(
    trajectory,
    camera: Cameras,
    renderer: Renderer,
    background: np.ndarray,  # [H, W, 3]
    device: str = "cpu",
    progress: bool = True,
    desc: str = "render",
    ply_dir: Path | None = None,
) -> tuple[np.ndarray, bool]:  # [T, H, W, 3] uint8, all finite
    """Frames of a ``GaussianTrajectory``; frames after its rest frame repeat the last one."""
    from tqdm import tqdm

    from physgm.pipeline.outputs import to_uint8

    n = len(trajectory)
    rest = trajectory.rest_frame
    frames = np.empty((n, camera.height, camera.width, 3), np.uint8)
    finite = bool(np.isfinite(trajectory.x).all() and np.isfinite(trajectory.F).all())
    if ply_dir is not None:
        ply_dir.mkdir(parents=True, exist_ok=True)
    for t in tqdm(range(n), desc=desc, unit="frame", disable=not progress, leave=False):
        path = None if ply_dir is None else ply_dir / f"frame_{t:04d}.ply"
        if rest is not None and t >= rest and t > 0:
            frames[t] = frames[t - 1]  # the object is still: the simulator holds the state
            if path is not None:
                shutil.copyfile(ply_dir / f"frame_{t - 1:04d}.ply", path)
            continue
        g = trajectory.gaussians_at(t)
        ok = finite_gaussians(g)
        img = render_gaussians(g, camera, renderer, background, device) if ok else np.zeros_like(background)
        finite = finite and ok and bool(np.isfinite(img).all())
        frames[t] = to_uint8(img)
        if path is not None:
            write_ply(g, path)
    return frames, finite
