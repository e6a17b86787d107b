"""A simulated trajectory turned into video frames over a background: the one way every clip is drawn.

The pipeline's videos, the data generator's reference drop videos and the DPO rollouts that are
scored against them all render here, so a rollout and its reference differ only by the physics.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch

from physgm.cameras import Cameras
from physgm.gaussians import Gaussians
from physgm.render.api import Renderer
from physgm.render.validate import all_finite


class Trajectory(Protocol):
    """What rendering needs of a simulated trajectory (``physgm.sim.gaussian_trajectory``)."""

    rest_frame: int | None  # first frame of the still tail (it repeats the frame before), or None

    def __len__(self) -> int: ...

    def gaussians_at(self, t: int) -> Gaussians: ...

    def reordered(self, index: torch.Tensor) -> Trajectory:
        """The same trajectory with its Gaussians in the order ``index`` [N] gives."""
        ...


def finite_gaussians(g: Gaussians) -> bool:
    return all(all_finite(t) for t in (g.means, g.quats, g.scales, g.opacities, g.colors))


@dataclass
class Shot:
    """How every frame of a clip is drawn: one camera, a renderer, and what lies behind the object."""

    camera: Cameras  # one camera
    renderer: Renderer
    background: np.ndarray  # [H, W, 3] (or broadcastable to it) float in [0, 1]
    device: str = "cpu"

    def draw(self, g: Gaussians) -> np.ndarray:  # [H, W, 3] float
        """One image of ``g`` composited over the background."""
        g, cam = g.to(self.device), self.camera.to(self.device)
        with torch.no_grad():
            rgb, alpha, _ = self.renderer(
                g.means, g.quats, g.scales, g.opacities, g.colors, cam.viewmats, cam.Ks, cam.width, cam.height
            )
        rgb, alpha = rgb[0].cpu().numpy(), alpha[0].cpu().numpy()
        return rgb + (1.0 - alpha) * self.background  # the renderer's rgb has no background (premultiplied)


def front_to_back(means: torch.Tensor, camera: Cameras) -> torch.Tensor:  # [N, 3] -> [N] int64
    """The Gaussians' order by depth from ``camera`` (its first view).

    Drawn in this order, the rasteriser's depth sort leaves them about where they are, so its
    per-Gaussian reads run through memory front to back instead of jumping (docs/measurements.md,
    "The render stage of a large .ply"). The picture changes only where two Gaussians lie at
    exactly the same depth.
    """
    view = camera.viewmats[0].to(means)
    return torch.argsort(means @ view[2, :3] + view[2, 3], stable=True)


def render_trajectory(
    trajectory: Trajectory, shot: Shot, progress: bool = False, desc: str = "render"
) -> tuple[np.ndarray, bool]:  # frames [T, H, W, 3] uint8, all finite
    """Frames of ``trajectory``; frames after its rest frame repeat the last one drawn.

    A frame whose Gaussians or pixels are not finite is drawn black and the second return is
    False; the caller decides whether that stops it (nothing here writes a file).
    """
    from tqdm import tqdm

    n, rest = len(trajectory), trajectory.rest_frame
    if n:
        trajectory = trajectory.reordered(front_to_back(trajectory.gaussians_at(0).means, shot.camera))
    h, w = shot.camera.height, shot.camera.width
    black = np.zeros((h, w, 3), np.float32)
    frames = np.empty((n, h, w, 3), np.uint8)
    finite = True
    for t in tqdm(range(n), desc=desc, unit="frame", disable=not progress, leave=False):
        if rest is not None and t >= rest and t > 0:
            frames[t] = frames[t - 1]  # the object is still: the simulator holds the state
            continue
        g = trajectory.gaussians_at(t)
        ok = finite_gaussians(g)
        img = shot.draw(g) if ok else black
        finite = finite and ok and bool(np.isfinite(img).all())
        frames[t] = np.round(np.clip(img, 0.0, 1.0) * 255.0).astype(np.uint8)
    return frames, finite
