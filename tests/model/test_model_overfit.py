"""The whole model can fit one tiny batch (a trainability check, not the pretraining loss).

Targets: fixed physics labels per scene (cross-entropy + Gaussian NLL through ``log_prob_terms``)
and the depth map of a sphere seen by the input cameras for the Gaussian head. The real
pretraining loss renders the Gaussians; it lives in the training stage, not here.
"""

from __future__ import annotations

import torch

from physgm.cameras import Cameras, pixel_rays
from physgm.model import PhysGM, PhysicsSample
from physgm.model.posterior import normalise_log10_E, normalise_nu


def test_overfits_one_batch(small_config, make_batch):
    torch.manual_seed(0)
    model = PhysGM(small_config(near=0.5, far=2.5, max_offset=0.0))
    batch = make_batch(4, 1, 16, 16, seed=2)
    labels = PhysicsSample(
        material=torch.tensor([[3], [7], [11], [0]]),
        log10_E=torch.tensor([[4.0], [6.5], [9.0], [11.0]]),
        nu=torch.tensor([[0.05], [0.2], [0.35], [0.45]]),
    )
    target_depth = _sphere_depth(batch["c2w"], batch["Ks"], 16, 16, radius=0.5)  # [4, 256]
    opt = torch.optim.Adam(model.parameters(), lr=2e-3)

    def losses():
        out = model(batch["images"], batch["masks"], batch["c2w"], batch["Ks"])
        log_p, log_E, log_nu = out.physics.log_prob_terms(labels)
        depth_mse = (out.gaussians.depths - target_depth).square().mean()
        return out, -log_p.mean(), -(log_E + log_nu).mean(), depth_mse

    out0, ce0, nll0, depth0 = losses()
    err0 = _mean_errors(out0.physics, labels)
    for _ in range(250):
        _, ce, nll, depth = losses()
        opt.zero_grad()
        (ce + nll + 10.0 * depth).backward()
        opt.step()
    out1, ce1, nll1, depth1 = losses()
    err1 = _mean_errors(out1.physics, labels)
    assert ce1 < ce0 / 10, (ce0, ce1)
    assert err1 < err0 / 10, (err0, err1)
    assert nll1 < nll0 - 3.0, (nll0, nll1)  # the NLL can go negative, so compare differences
    assert depth1 < depth0 / 10, (depth0, depth1)
    assert torch.equal(out1.physics.material_logits.argmax(-1), labels.material[:, 0])


def _mean_errors(post, labels: PhysicsSample) -> float:
    """Squared error of the predicted normalised means against the labels."""
    e = (post.z_E_mean - normalise_log10_E(labels.log10_E[:, 0])).square().mean()
    n = (post.z_nu_mean - normalise_nu(labels.nu[:, 0])).square().mean()
    return float((e + n).detach())


def _sphere_depth(c2w, Ks, height: int, width: int, radius: float):
    """Ray distance to a sphere at the origin; rays that miss it take their closest approach."""
    b, v = c2w.shape[:2]
    origins, dirs = pixel_rays(Cameras(c2w.reshape(-1, 4, 4), Ks.reshape(-1, 3, 3), width, height))
    t_close = -(origins * dirs).sum(-1)  # [B*V, H, W]
    miss2 = (origins.square().sum(-1) - t_close**2).clamp(min=0)
    inside = (radius**2 - miss2).clamp(min=0).sqrt()
    return (t_close - inside).reshape(b, v * height * width)
