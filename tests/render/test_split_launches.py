"""The CPU splits the per-pair and per-entry launches of the warp backend over threads, at image
and scene boundaries; the result must not depend on it."""

from __future__ import annotations

import pytest
import torch

from physgm.render import warp_backend
from physgm.render.settings import RasterSettings
from physgm.render.torch_backend import rasterize_torch

SPLIT_KERNELS = {"pair_bounds_kernel", "bin_entries_kernel", "scatter_entry_grads_kernel", "project_vjp_kernel"}


def batched_scene(kit, num_b: int, num_c: int, num_n: int = 150, width: int = 40, height: int = 32) -> dict:
    """num_b different objects, each seen by its own num_c cameras ([B, N, ...], [B, C, ...], float32)."""
    objects = [kit.random_gaussians(num_n, seed=10 + b) for b in range(num_b)]
    cameras = [kit.orbit_cameras(num_c, width, height, seed=b) for b in range(num_b)]
    scene = {k: torch.stack([o[k] for o in objects]).float() for k in kit.GRAD_KEYS}
    scene["viewmats"] = torch.stack([c[0] for c in cameras]).float()
    scene["Ks"] = torch.stack([c[1] for c in cameras]).float()
    return scene


def render(scene: dict, fn, settings: RasterSettings):
    """rgb, alpha and the gradients of a fixed random loss."""
    leaves = {k: scene[k].clone().requires_grad_() for k in ("means", "quats", "scales", "opacities", "colors")}
    rgb, alpha, _ = fn(*leaves.values(), scene["viewmats"], scene["Ks"], settings)
    gen = torch.Generator().manual_seed(3)
    loss = (rgb * torch.randn(rgb.shape, generator=gen)).sum() + (alpha * torch.randn(alpha.shape, generator=gen)).sum()
    loss.backward()
    return rgb.detach(), alpha.detach(), {k: v.grad for k, v in leaves.items()}


@pytest.mark.parametrize(("num_b", "num_c", "threads"), [(3, 2, 2), (2, 3, 3), (1, 3, 2), (2, 1, 2)])
def test_split_launches_match_one_thread_and_the_torch_twin(kit, monkeypatch, num_b, num_c, threads):
    scene = batched_scene(kit, num_b, num_c)
    serial = render(scene, warp_backend.rasterize_warp, RasterSettings(40, 32, num_threads=1))

    split = []
    run_parallel = warp_backend._run_parallel

    def recording(kernel, launches, device):
        split.append((kernel.key, len(launches)))
        run_parallel(kernel, launches, device)

    monkeypatch.setattr(warp_backend, "_MIN_SPLIT", 1)  # split even these small launches
    monkeypatch.setattr(warp_backend, "_MIN_SPLIT_BOUNDS", 1)
    monkeypatch.setattr(warp_backend, "_run_parallel", recording)
    parallel = render(scene, warp_backend.rasterize_warp, RasterSettings(40, 32, num_threads=threads))

    # per image: bounds and binning split with 2 or more images; per scene: with 2 or more scenes
    expected = {"pair_bounds_kernel", "bin_entries_kernel"} if num_b * num_c > 1 else set()
    if num_b > 1:
        expected |= {"scatter_entry_grads_kernel", "project_vjp_kernel"}
    assert {key for key, parts in split if key in SPLIT_KERNELS and parts > 1} == expected
    for a, b in zip(serial[:2], parallel[:2], strict=True):
        assert torch.equal(a, b)  # each pixel and each Gaussian's sum is computed by one thread, in order
    for name in serial[2]:
        assert torch.equal(serial[2][name], parallel[2][name]), name

    rgb_t, alpha_t, grads_t = render(scene, rasterize_torch, RasterSettings(40, 32))
    assert alpha_t.max() > 0.5
    assert (parallel[0] - rgb_t).abs().max() <= 1e-4
    assert (parallel[1] - alpha_t).abs().max() <= 1e-4
    for name, ref in grads_t.items():
        assert (parallel[2][name] - ref).norm() <= 1e-3 * ref.norm(), name


def test_cuts_fall_on_units():
    assert warp_backend._cuts(12, 4, 2) == [0, 4, 12]  # 3 scenes of 4 pairs: 1 + 2
    assert warp_backend._cuts(12, 4, 3) == [0, 4, 8, 12]
    assert warp_backend._cuts(4, 4, 2) == [0, 4]  # one scene cannot be split
    assert warp_backend._cuts(0, 0, 2) == [0, 0]  # no Gaussians
    assert warp_backend._cuts(7, 1, 1) == [0, 7]
