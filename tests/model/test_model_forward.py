"""PhysGM forward pass: shapes, masking, ray geometry, view/batch structure, config round trips."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from physgm.cameras import Cameras
from physgm.gaussians import Gaussians
from physgm.model import PhysGM, PhysGMConfig, load_physgm

CONF_DIR = Path(__file__).resolve().parents[2] / "conf"


def run(model, batch):
    return model(batch["images"], batch["masks"], batch["c2w"], batch["Ks"])


@pytest.mark.parametrize(("views", "layers"), [(1, 1), (4, 1), (1, 2)])
def test_shapes_finite_and_mask_count(small_config, make_batch, views, layers):
    config = small_config(layers=layers)
    model = PhysGM(config).eval()
    batch = make_batch(2, views, 32, 48)
    with torch.no_grad():
        out = run(model, batch)
    g, n = out.gaussians, layers * views * 32 * 48
    shapes = {
        "means": (2, n, 3),
        "quats": (2, n, 4),
        "scales": (2, n, 3),
        "opacities": (2, n),
        "colors": (2, n, 3),
        "depths": (2, n),
    }
    for name, shape in shapes.items():
        value = getattr(g, name)
        assert tuple(value.shape) == shape, name
        assert torch.isfinite(value).all(), name
    assert (g.views, g.height, g.width, g.layers) == (views, 32, 48, layers)
    torch.testing.assert_close(g.quats.norm(dim=-1), torch.ones(2, n))
    assert (g.scales >= 0.0005 - 1e-9).all() and (g.scales <= 0.1 + 1e-9).all()
    assert (g.colors >= 0).all() and (g.colors <= 1).all()
    # Gaussians exist exactly where the mask is above the threshold, and nowhere else is visible.
    expected_valid = (batch["masks"].reshape(2, -1) > config.gaussian_head.mask_threshold).repeat(1, layers)
    assert torch.equal(g.valid, expected_valid)
    assert torch.equal(g.count, expected_valid.sum(dim=1))
    assert 0 < g.count.min() < n
    assert (g.opacities[~g.valid] == 0).all() and (g.opacities[g.valid] > 0).all()
    # to_gaussians keeps exactly the valid rows, in order.
    gs = g.to_gaussians(1)
    assert isinstance(gs, Gaussians) and len(gs) == int(g.count[1])
    torch.testing.assert_close(gs.means, g.means[1][g.valid[1]])
    torch.testing.assert_close(gs.colors, g.colors[1][g.valid[1]])
    p = out.physics
    assert p.material_logits.shape == (2, 15)
    for t in (p.z_E_mean, p.z_E_logvar, p.z_nu_mean, p.z_nu_logvar):
        assert t.shape == (2,) and torch.isfinite(t).all()


def test_means_on_pixel_rays_within_near_far(small_config, make_batch):
    """With the offset disabled every mean projects to its own pixel centre at depth in [near, far]."""
    cfg = small_config(max_offset=0.0, near=0.3, far=1.7)
    model = PhysGM(cfg).eval()
    batch = make_batch(2, 3, 16, 24, seed=3)
    with torch.no_grad():
        g = run(model, batch).gaussians
    cams = Cameras(batch["c2w"].reshape(6, 4, 4), batch["Ks"].reshape(6, 3, 3), 24, 16)
    means = g.means.reshape(6, 16 * 24, 3)
    cam_pts = means @ cams.viewmats[:, :3, :3].transpose(1, 2) + cams.viewmats[:, None, :3, 3]
    uv = cam_pts @ cams.Ks.transpose(1, 2)
    uv = uv[..., :2] / uv[..., 2:]
    vv, uu = torch.meshgrid(torch.arange(16) + 0.5, torch.arange(24) + 0.5, indexing="ij")
    pixel_centres = torch.stack([uu, vv], -1).reshape(1, -1, 2).expand(6, -1, -1)
    torch.testing.assert_close(uv, pixel_centres, atol=2e-3, rtol=0)
    distance = (means - cams.centers[:, None]).norm(dim=-1).reshape(2, -1)
    torch.testing.assert_close(distance, g.depths, atol=1e-5, rtol=1e-5)
    assert (g.depths >= 0.3).all() and (g.depths <= 1.7).all()
    assert (cam_pts[..., 2] > 0).all()  # in front of the camera


def test_centre_depth_prior_starts_at_the_object_centre_and_reaches_scene_radius():
    """depth_prior="centre": raw 0 puts a mean on the ray's closest point to the origin, raw -> +-inf
    moves it scene_radius towards or away from the camera, and [near, far] still bounds it."""
    from dataclasses import replace

    from physgm.model import GaussianHeadConfig
    from physgm.model.gaussian_head import RAW_CHANNELS, GaussianActivations

    gen = torch.Generator().manual_seed(0)
    n = 64
    origins = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen), dim=-1) * 1.8
    # rays from the camera towards points within 0.3 of the origin
    directions = torch.nn.functional.normalize(0.3 * torch.randn(n, 3, generator=gen) - origins, dim=-1)
    rgb = torch.rand(n, 3, generator=gen)
    cfg = replace(
        GaussianHeadConfig(), depth_prior="centre", scene_radius=0.4, max_offset=0.0, near=0.001, far=2.0
    )
    act = GaussianActivations(cfg)

    def depths(value: float) -> torch.Tensor:
        raw = {k: torch.zeros(n, c) for k, c in RAW_CHANNELS.items()}
        raw["depth"] = torch.full((n, 1), value)
        out = act(raw, rgb, origins, directions)
        torch.testing.assert_close(out["means"], origins + out["depths"][:, None] * directions)
        return out["depths"]

    closest = -(origins * directions).sum(-1)  # distance to the foot of the perpendicular from 0
    torch.testing.assert_close(depths(0.0), closest)
    torch.testing.assert_close(depths(-30.0), closest - 0.4)
    torch.testing.assert_close(depths(30.0), (closest + 0.4).clamp(max=2.0))
    assert (depths(30.0) == 2.0).any()  # some rays reach far and are clamped
    with pytest.raises(ValueError, match="depth_prior"):
        GaussianActivations(replace(cfg, depth_prior="centered"))
    with pytest.raises(ValueError, match="scene_radius"):
        GaussianActivations(replace(cfg, scene_radius=0.0))


def test_view_permutation_and_batch_independence(small_config, make_batch):
    model = PhysGM(small_config()).eval()
    batch = make_batch(2, 3, 16, 16, seed=1)
    perm = torch.tensor([2, 0, 1])
    with torch.no_grad():
        out = run(model, batch)
        out_perm = run(model, {k: v[:, perm] for k, v in batch.items()})
        out_first = run(model, {k: v[:1] for k, v in batch.items()})
    # No view-index embedding: permuting views permutes the Gaussians and keeps the physics.
    means = out.gaussians.means.reshape(2, 3, -1, 3)
    torch.testing.assert_close(
        out_perm.gaussians.means.reshape(2, 3, -1, 3), means[:, perm], atol=1e-5, rtol=1e-5
    )
    torch.testing.assert_close(
        out_perm.physics.material_logits, out.physics.material_logits, atol=1e-5, rtol=1e-5
    )
    # Scenes in a batch do not see each other.
    torch.testing.assert_close(out_first.gaussians.means, out.gaussians.means[:1], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(out_first.physics.z_E_mean, out.physics.z_E_mean[:1], atol=1e-5, rtol=1e-5)
    # ... but views of one scene do see each other.
    with torch.no_grad():
        alone = run(model, {k: v[:, :1] for k, v in batch.items()})
    assert not torch.allclose(alone.physics.material_logits, out.physics.material_logits, atol=1e-4)


@pytest.mark.parametrize("layers", [1, 2])
def test_every_parameter_gets_gradient_and_split_is_a_partition(small_config, make_batch, layers):
    model = PhysGM(small_config(layers=layers))
    out = run(model, make_batch(1, 2, 16, 16))
    g, p = out.gaussians, out.physics
    loss = sum(t.square().mean() for t in (g.means, g.quats, g.scales, g.opacities, g.colors))
    loss = (
        loss
        + p.material_logits.square().mean()
        + (p.z_E_mean + p.z_E_logvar + p.z_nu_mean + p.z_nu_logvar).sum()
    )
    loss.backward()
    dead = [n for n, q in model.named_parameters() if q.grad is None or not torch.isfinite(q.grad).all()]
    assert not dead
    physics = {id(q) for q in model.physics_parameters()}
    rest = {id(q) for q in model.backbone_parameters()}
    assert physics and rest and not physics & rest
    assert physics | rest == {id(q) for q in model.parameters()}
    assert physics == {id(q) for q in model.physics_head.parameters()}


def test_bad_inputs_say_what_is_wrong(small_config, make_batch):
    model = PhysGM(small_config()).eval()
    batch = make_batch(1, 1, 20, 16)
    with pytest.raises(ValueError, match="multiple of the patch size 8"):
        run(model, batch)
    batch = make_batch(1, 2, 16, 16)
    with pytest.raises(ValueError, match=r"masks must have shape \[1, 2, 1, 16, 16\]"):
        model(batch["images"], batch["masks"][:, :1], batch["c2w"], batch["Ks"])
    with pytest.raises(ValueError, match="out_layers"):
        PhysGM(PhysGMConfig.from_dict({"backbone": {"depth": 3, "out_layers": [0, 1, 2, 3]}}))
    with pytest.raises(ValueError, match="unknown key"):
        PhysGMConfig.from_dict({"backbone": {"widht": 64}})
    with pytest.raises(ValueError, match="layers must be at least 1, got 0"):
        PhysGM(small_config(layers=0))


def test_checkpoint_round_trip_without_hydra(small_config, make_batch):
    model = PhysGM(small_config()).eval()
    config = model.config.to_dict()
    assert PhysGMConfig.from_dict(config) == model.config
    clone = load_physgm(config, model.state_dict()).eval()
    batch = make_batch(1, 2, 16, 16)
    with torch.no_grad():
        a, b = run(model, batch), run(clone, batch)
    assert torch.equal(a.gaussians.means, b.gaussians.means)
    assert torch.equal(a.physics.material_logits, b.physics.material_logits)


@pytest.mark.parametrize("name", ["physgm", "physgm_small", "physgm_paper"])
def test_hydra_configs_map_onto_dataclass(name):
    hydra = pytest.importorskip("hydra")
    from omegaconf import OmegaConf

    with hydra.initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = hydra.compose(config_name=None, overrides=[f"+model={name}"])
    data = OmegaConf.to_container(cfg.model, resolve=True)
    assert data.pop("_target_") == "physgm.model.build_physgm"
    config = PhysGMConfig.from_dict(data)
    assert config.physics_head.num_materials == 15
    if name == "physgm":
        assert config == PhysGMConfig()  # the dataclass defaults are the tiny YAML model
    if name == "physgm_paper":
        b = config.backbone
        assert (b.depth, b.width, b.head_dim, b.encoder.kind, b.encoder.patch_size) == (
            24,
            1024,
            64,
            "dinov3",
            16,
        )
    if config.backbone.encoder.kind == "vit":
        from hydra.utils import instantiate

        assert isinstance(instantiate(cfg.model), PhysGM)


def test_num_materials_matches_material_table():
    materials = pytest.importorskip("physgm.physics.materials")
    assert len(materials.MATERIAL_NAMES) == PhysGMConfig().physics_head.num_materials
