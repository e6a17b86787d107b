"""``stage.init_ckpt``: stage 1 starts from a checkpoint's weights, widening a layer that takes new inputs."""

from __future__ import annotations

from operator import attrgetter

import pytest
import torch

from physgm.errors import UserError
from physgm.model import PhysGM
from physgm.model.checkpoint import save_checkpoint
from physgm.train.run import run
from physgm.train.warm_start import warm_start
from tests.model_configs import tiny_config
from tests.train.test_pretrain import compose_train, tiny_overrides

OUTPUT_CONV = "gaussian_head.dpt.output.0.weight"


def _started(tmp_path, **new) -> tuple[PhysGM, PhysGM, object]:
    """A default tiny model saved, and a model of config ``new`` warm-started from it:
    (source, model, warm_start report)."""
    torch.manual_seed(0)
    source = PhysGM(tiny_config()).eval()
    save_checkpoint(source, tmp_path / "source.ckpt")
    torch.manual_seed(1)
    model = PhysGM(tiny_config(**new)).eval()
    return source, model, warm_start(model, tmp_path / "source.ckpt")


def _assert_same(got, want, *outputs: str) -> None:
    """The named outputs (dotted paths of the model's output, e.g. ``gaussians.means``) are equal."""
    for name in outputs:
        torch.testing.assert_close(attrgetter(name)(got), attrgetter(name)(want), rtol=0, atol=0, msg=name)


def _views(count: int, g: torch.Generator) -> tuple[torch.Tensor, ...]:
    """``count`` random 32 px views of one scene on the camera axis, 1.5 m back and 0.1 m apart:
    (images, masks, c2w, Ks), each [1, count, ...]."""
    images, masks = torch.rand(1, count, 3, 32, 32, generator=g), torch.ones(1, count, 1, 32, 32)
    c2w = torch.eye(4).expand(1, count, 4, 4).clone()
    c2w[0, :, 2, 3] = -1.5 - 0.1 * torch.arange(count)
    Ks = torch.tensor([[32.0, 0.0, 16.0], [0.0, 32.0, 16.0], [0.0, 0.0, 1.0]]).expand(1, count, 3, 3)
    return images, masks, c2w, Ks


def test_the_hull_model_starts_from_a_range_checkpoint_and_its_head_computes_the_same(tmp_path):
    torch.manual_seed(0)
    source = PhysGM(tiny_config(depth_prior="range")).eval()
    save_checkpoint(source, tmp_path / "range.ckpt")
    torch.manual_seed(1)
    model = PhysGM(tiny_config(depth_prior="hull")).eval()
    report = warm_start(model, tmp_path / "range.ckpt")

    assert report.widened == [OUTPUT_CONV]
    assert report.new == []
    assert len(report.copied) == len(source.state_dict()) - 1
    for name, value in source.state_dict().items():
        if name != OUTPUT_CONV:
            torch.testing.assert_close(model.state_dict()[name], value, rtol=0, atol=0)
    grown = model.state_dict()[OUTPUT_CONV]
    old = source.state_dict()[OUTPUT_CONV]
    assert grown.shape[1] == old.shape[1] + 2  # the hull segment's start and length
    torch.testing.assert_close(grown[:, : old.shape[1]], old, rtol=0, atol=0)
    assert not grown[:, old.shape[1] :].any()

    # The widened DPT head gives the source's raw outputs whatever guide it is handed.
    tokens = [torch.randn(2, 16, 32) for _ in range(4)]
    images = torch.rand(2, 3, 32, 32)
    with torch.no_grad():
        want = source.gaussian_head.dpt(tokens, images)
        got = model.gaussian_head.dpt(tokens, images, guide=torch.rand(2, 2, 32, 32))
    assert len(want) == len(got) == 1
    for name in want[0]:
        torch.testing.assert_close(got[0][name], want[0][name], rtol=0, atol=1e-6)


def test_geometry_blocks_start_as_copies_of_the_blocks_they_duplicate(tmp_path):
    """A model whose Gaussian head has its own last 3 blocks, started from one without: the copies
    hold the shared blocks' weights, so both heads compute exactly what the checkpoint's did."""
    source, model, report = _started(tmp_path, geometry_blocks=3)

    assert report.new == [] and report.widened == []
    assert len(report.copied) == len(source.state_dict())
    assert len(report.branched) == 3 * len(source.backbone.blocks[0].state_dict())
    torch.testing.assert_close(
        model.backbone.geometry_blocks[0].attn.qkv.weight,
        source.backbone.blocks[1].attn.qkv.weight,
        rtol=0,
        atol=0,
    )
    g = torch.Generator().manual_seed(0)
    images, masks, c2w, Ks = _views(2, g)
    with torch.no_grad():
        want, got = source(images, masks, c2w, Ks), model(images, masks, c2w, Ks)
    _assert_same(got, want, "global_tokens", "gaussians.means", "gaussians.colors")

    # Once the copies differ, only the Gaussians change.
    with torch.no_grad():
        for p in model.backbone.geometry_blocks.parameters():
            p.add_(0.05 * torch.randn(p.shape, generator=g))
        moved = model(images, masks, c2w, Ks)
    _assert_same(moved, want, "global_tokens", "physics.z_E_mean")
    assert not torch.allclose(moved.gaussians.means, want.gaussians.means)

    with pytest.raises(ValueError, match="geometry_blocks must be in"):
        PhysGM(tiny_config(geometry_blocks=5))


def test_more_geometry_blocks_keep_the_trained_copies_last_and_copy_the_blocks_before(tmp_path):
    """A checkpoint whose Gaussian head has trained copies of the last 2 blocks, started as a model
    with copies of the last 3: the trained copies become its last two, the first new one copies the
    shared block it duplicates, and both heads compute exactly what the checkpoint's did."""
    torch.manual_seed(0)
    source = PhysGM(tiny_config(geometry_blocks=2)).eval()
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():  # trained copies: no longer equal to the shared blocks
        for p in source.backbone.geometry_blocks.parameters():
            p.add_(0.05 * torch.randn(p.shape, generator=g))
    save_checkpoint(source, tmp_path / "two.ckpt")
    torch.manual_seed(1)
    model = PhysGM(tiny_config(geometry_blocks=3)).eval()
    report = warm_start(model, tmp_path / "two.ckpt")

    per_block = len(source.backbone.blocks[0].state_dict())
    assert report.new == [] and report.widened == [] and len(report.branched) == per_block
    assert all(name.startswith("backbone.geometry_blocks.0.") for name in report.branched)
    for j, copy in enumerate(model.backbone.geometry_blocks):
        want = source.backbone.blocks[1] if j == 0 else source.backbone.geometry_blocks[j - 1]
        for (name, value), expected in zip(
            copy.state_dict().items(), want.state_dict().values(), strict=True
        ):
            torch.testing.assert_close(value, expected, rtol=0, atol=0, msg=f"copy {j}: {name}")
    images, masks, c2w, Ks = _views(2, g)
    with torch.no_grad():
        want, got = source(images, masks, c2w, Ks), model(images, masks, c2w, Ks)
    _assert_same(got, want, "global_tokens", "physics.z_E_mean", "gaussians.means", "gaussians.colors")


def test_a_second_gaussian_layer_starts_as_a_faint_copy_of_the_first(tmp_path):
    """A two-layer model started from a one-layer checkpoint: the first layer's Gaussians are the
    checkpoint's to the bit, and each second-layer Gaussian sits where its first-layer twin does
    with its opacity's logit lowered by layer_opacity_shift, so the start renders almost as before."""
    source, model, report = _started(tmp_path, layers=2)

    layer_weights = ["gaussian_head.dpt.layer_outputs.0.weight", "gaussian_head.dpt.layer_outputs.0.bias"]
    assert report.new == [] and report.widened == [] and report.branched == layer_weights
    assert len(report.copied) == len(source.state_dict())
    g = torch.Generator().manual_seed(0)
    images, masks, c2w, Ks = _views(1, g)
    with torch.no_grad():
        want, got = source(images, masks, c2w, Ks).gaussians, model(images, masks, c2w, Ks).gaussians
    n = 32 * 32
    assert got.layers == 2 and got.means.shape[1] == 2 * n
    for name in ("means", "scales", "colors", "opacities"):
        torch.testing.assert_close(getattr(got, name)[:, :n], getattr(want, name), rtol=0, atol=0)
        if name != "opacities":
            torch.testing.assert_close(getattr(got, name)[:, n:], getattr(want, name), rtol=0, atol=0)
    shift = model.config.gaussian_head.layer_opacity_shift
    torch.testing.assert_close(
        got.opacities[:, n:],
        torch.sigmoid(torch.logit(want.opacities.double()) + shift).float(),
        atol=1e-6,
        rtol=1e-4,
    )
    assert (got.opacities[:, n:] < want.opacities).all()


def test_another_architecture_is_refused_with_the_weights_named(tmp_path):
    save_checkpoint(PhysGM(tiny_config(width=32)), tmp_path / "w32.ckpt")
    with pytest.raises(UserError, match="different model.*weights of another shape.*backbone"):
        warm_start(PhysGM(tiny_config(width=48)), tmp_path / "w32.ckpt")
    with pytest.raises(UserError, match="no PhysGM checkpoint"):
        warm_start(PhysGM(tiny_config()), tmp_path / "missing.ckpt")


def test_a_run_with_init_ckpt_starts_from_those_weights(tiny_dataset, tmp_path):
    """Through train.py's config: a from-scratch run, then a hull run from its checkpoint at lr 0,
    whose saved weights are the first run's (the widened conv's new channels zero)."""
    steps = ["trainer.max_steps=1", "trainer.limit_val_batches=0"]
    run(compose_train([*tiny_overrides(tiny_dataset, tmp_path / "a"), *steps]))
    first = torch.load(tmp_path / "a" / "checkpoints" / "last.ckpt", weights_only=False)["state_dict"]
    run(
        compose_train(
            [
                *tiny_overrides(tiny_dataset, tmp_path / "b"),
                *steps,
                "stage.optim.lr=0",
                "model.gaussian_head.depth_prior=hull",
                f"stage.init_ckpt={tmp_path / 'a' / 'checkpoints' / 'last.ckpt'}",
            ]
        )
    )
    second = torch.load(tmp_path / "b" / "checkpoints" / "last.ckpt", weights_only=False)["state_dict"]
    assert set(second) == set(first)
    for name, value in first.items():
        got = second[name][:, : value.shape[1]] if name == "model." + OUTPUT_CONV else second[name]
        torch.testing.assert_close(got, value, rtol=0, atol=0, msg=name)
    width = first["model." + OUTPUT_CONV].shape[1]
    assert not second["model." + OUTPUT_CONV][:, width:].any()
