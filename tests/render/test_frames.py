"""A trajectory to frames: held frames repeat, the background shows where nothing is, NaN is reported."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
import torch

from physgm.cameras import orbit_cameras
from physgm.gaussians import Gaussians
from physgm.render import Renderer
from physgm.render.frames import Shot, finite_gaussians, front_to_back, render_trajectory


@dataclass
class Falling:
    """A blob moving down 5 cm a frame until ``rest_frame``: what the renderer reads of a trajectory."""

    blob: Gaussians
    n: int
    rest_frame: int | None

    def __len__(self) -> int:
        return self.n

    def gaussians_at(self, t: int) -> Gaussians:
        shift = torch.tensor([0.0, 0.0, -0.05 * t])
        return Gaussians(
            self.blob.means + shift, self.blob.quats, self.blob.scales, self.blob.opacities, self.blob.colors
        )

    def reordered(self, index: torch.Tensor) -> Falling:
        return Falling(self.blob[index], self.n, self.rest_frame)


def _blob() -> Gaussians:
    n = 20
    gen = torch.Generator().manual_seed(0)
    return Gaussians(
        torch.randn(n, 3, generator=gen) * 0.05,
        torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1),
        torch.full((n, 3), 0.04),
        torch.full((n,), 0.9),
        torch.tensor([[0.1, 0.2, 0.8]]).repeat(n, 1),
    )


def test_frames_move_until_rest_then_repeat_over_the_background():
    cam = orbit_cameras([0.0], [0.0], 1.0, 40.0, 24, 24)
    traj = Falling(_blob(), n=5, rest_frame=3)
    frames, finite = render_trajectory(traj, Shot(cam, Renderer(backend="torch"), np.array([1.0, 1.0, 1.0])))
    assert finite and frames.shape == (5, 24, 24, 3) and frames.dtype == np.uint8
    assert not np.array_equal(frames[1], frames[2])  # still moving
    assert np.array_equal(frames[3], frames[2]) and np.array_equal(frames[4], frames[2])  # held
    assert (frames[0, 0, 0] == 255).all()  # a corner shows the white background
    blue = frames[0].astype(int)
    assert (blue[..., 2] - blue[..., 0]).max() > 100  # the blue blob is drawn


def test_non_finite_gaussians_give_a_black_frame_and_say_so():
    cam = orbit_cameras([0.0], [0.0], 1.0, 40.0, 16, 16)
    blob = _blob()
    blob.means[0, 0] = float("nan")
    frames, finite = render_trajectory(
        Falling(blob, 2, None), Shot(cam, Renderer(backend="torch"), np.ones(3))
    )
    assert not finite and (frames == 0).all()


def test_frames_are_drawn_front_to_back_with_the_pixels_of_the_order_given():
    # render_trajectory hands the rasteriser the Gaussians in depth order from the camera, so
    # its reads run through memory in order; with no two at one depth the pixels stay the same.
    gen = torch.Generator().manual_seed(4)
    n = 400
    blob = Gaussians(
        torch.randn(n, 3, generator=gen) * 0.1,
        torch.nn.functional.normalize(torch.randn(n, 4, generator=gen), dim=-1),
        torch.rand(n, 3, generator=gen) * 0.03 + 0.005,
        torch.rand(n, generator=gen) * 0.8 + 0.1,
        torch.rand(n, 3, generator=gen),
    )
    cam = orbit_cameras([20.0], [10.0], 1.0, 40.0, 48, 48)
    order = front_to_back(blob.means, cam)
    depth = blob.means @ cam.viewmats[0, 2, :3] + cam.viewmats[0, 2, 3]
    assert (depth[order].diff() > 0).all() and not torch.equal(order, torch.arange(n))
    shot = Shot(cam, Renderer(), np.array([0.2, 0.3, 0.4]))
    asked = []

    class Recorded(Falling):
        def reordered(self, index: torch.Tensor) -> Falling:
            asked.append(index)
            return super().reordered(index)

    traj = Recorded(blob, n=3, rest_frame=None)
    frames, finite = render_trajectory(traj, shot)
    assert finite and len(asked) == 1 and torch.equal(asked[0], order)
    for t in range(3):
        drawn = np.round(np.clip(shot.draw(traj.gaussians_at(t)), 0.0, 1.0) * 255.0).astype(np.uint8)
        assert np.array_equal(frames[t], drawn), t


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
@pytest.mark.parametrize("field", ["means", "quats", "scales", "opacities", "colors"])
def test_one_non_finite_number_anywhere_is_found(field, bad):
    blob = _blob()
    assert finite_gaussians(blob) and finite_gaussians(blob[:0])
    getattr(blob, field).view(-1)[7] = bad
    assert not finite_gaussians(blob)
