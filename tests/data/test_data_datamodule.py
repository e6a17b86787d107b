"""PhysAssetsDataModule: batch shapes, inputs inside targets, labels, corrupt assets."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from physgm.data.datamodule import Batch, Collate, FolderDataset, PhysAssetsDataModule
from physgm.data.format import AssetError, load_asset
from physgm.data.views import ViewConfig
from physgm.physics.materials import MATERIAL_NAMES


def _module(root, **kw):
    base = dict(batch_size=3, val_split="test", input_resolution=16, num_targets=8)
    return PhysAssetsDataModule(str(root), **{**base, **kw})


@pytest.mark.parametrize("p_single,views", [(1.0, 1), (0.0, 4)])
def test_batch_shapes_and_targets_include_inputs(tiny_root, p_single, views):
    dm = _module(tiny_root, p_single=p_single)
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    assert isinstance(batch, Batch) and len(batch) == 3 and batch.num_views == views
    assert batch.images.shape == (3, views, 3, 16, 16) and batch.masks.shape == (3, views, 1, 16, 16)
    assert batch.c2w.shape == (3, views, 4, 4) and batch.Ks.shape == (3, views, 3, 3)
    assert batch.target_images.shape == (3, 8, 3, 32, 32) and batch.target_masks.shape == (3, 8, 1, 32, 32)
    assert torch.equal(batch.target_index[:, :views], batch.input_index)
    assert torch.equal(batch.target_c2w[:, :views], batch.c2w)
    # Targets are distinct views; inputs are the canonical view and its 90-degree neighbours.
    assert all(len(set(row.tolist())) == 8 for row in batch.target_index)
    assert (batch.input_index[:, 0] == 0).all()
    if views == 4:
        assert batch.input_index.tolist() == [[0, 2, 4, 6]] * 3
    # Intrinsics follow the 2x downsampling of the inputs.
    torch.testing.assert_close(batch.Ks[..., :2, :], batch.target_Ks[:, :views, :2, :] / 2)
    assert batch.images.min() >= 0 and batch.images.max() <= 1 and batch.masks.max() > 0.5


def test_labels_come_from_annotation_and_truth(tiny_root):
    dm = _module(tiny_root, batch_size=4)
    dm.setup("test")
    batch = next(iter(dm.test_dataloader()))
    for i, aid in enumerate(batch.asset_ids):
        phys = json.loads((tiny_root / aid / "physical.json").read_text())
        ann = phys["annotation"]
        assert batch.material[i] == MATERIAL_NAMES.index(ann["material"])
        assert batch.true_material[i] == MATERIAL_NAMES.index(phys["material"])
        assert batch.log10_E[i] == pytest.approx(math.log10(ann["E"]))
        assert batch.nu[i] == pytest.approx(ann["nu"])
        assert batch.true_log10_E[i] == pytest.approx(math.log10(phys["E"]))
        assert batch.true_nu[i] == pytest.approx(phys["nu"])
    assert batch.true_known.all()


def test_images_are_views_composited_over_white(tiny_root):
    ds = FolderDataset(tiny_root, "train", ViewConfig(), deterministic=True)
    ex, _ = ds[0]
    asset = load_asset(tiny_root / ex.id)
    rgba = asset.load_rgba(ex.target_index.tolist())
    expect = rgba[..., :3] * rgba[..., 3:] + (1 - rgba[..., 3:])
    torch.testing.assert_close(ex.target_images, torch.from_numpy(expect).permute(0, 3, 1, 2))
    torch.testing.assert_close(ex.target_masks[:, 0], torch.from_numpy(rgba[..., 3]))
    # Deterministic (evaluation) examples repeat; training ones draw other extra targets.
    assert torch.equal(ds[0][0].target_index, ex.target_index)


def test_mixed_view_counts_never_share_a_batch(tiny_root):
    torch.manual_seed(0)
    dm = _module(tiny_root, p_single=0.5, batch_size=2)
    dm.setup("fit")
    counts = [b.num_views for _ in range(3) for b in dm.train_dataloader()]
    assert set(counts) == {1, 4}
    collate = Collate(0.5, deterministic=True)
    assert collate.num_views(["a", "b"]) == collate.num_views(["a", "b"])


def test_random_azimuth_keeps_inputs_ninety_degrees_apart(tiny_root):
    ds = FolderDataset(tiny_root, "train", ViewConfig(random_azimuth=True), deterministic=False)
    torch.manual_seed(1)
    firsts = set()
    for i in range(8):
        idx = ds[i][0].input_index.tolist()
        assert all(v < 8 for v in idx)  # elevation 0 ring
        assert [(v - idx[0]) % 8 for v in idx] == [0, 2, 4, 6]
        firsts.add(idx[0])
    assert len(firsts) > 1


def test_corrupt_asset_raises_with_its_name_or_is_skipped_and_counted(tiny_copy):
    train = (tiny_copy / "splits" / "train.txt").read_text().split()
    broken, truncated = train[0], train[1]
    (tiny_copy / broken / "physical.json").write_text("{}")
    for png in (tiny_copy / truncated / "rgba").glob("*.png"):
        png.write_bytes(png.read_bytes()[:50])  # passes the folder scan, fails when decoded
    with pytest.raises(AssetError, match=broken):
        FolderDataset(tiny_copy, "train", ViewConfig(), deterministic=True)
    with pytest.warns(UserWarning, match=f"skipped 1 malformed asset.*{broken}"):
        ds = FolderDataset(tiny_copy, "train", ViewConfig(), deterministic=True, on_corrupt="skip")
    assert set(ds.skipped) == {broken} and len(ds) == len(train) - 1
    pos = [a.id for a in ds.assets].index(truncated)
    ex, skipped = ds[pos]
    assert skipped == [truncated] and ex.id != truncated
    batch = Collate(0.0, True)([ds[pos], ds[(pos + 1) % len(ds)]])
    assert batch.skipped == [truncated] and len(batch) == 2
    ds.on_corrupt = "raise"  # the same dataset in strict mode names the undecodable asset
    with pytest.raises(AssetError, match=truncated):
        ds[pos]


def test_lightning_moves_typed_batches(tiny_root):
    dm = _module(tiny_root)
    dm.setup("fit")
    batch = next(iter(dm.val_dataloader()))
    moved = dm.transfer_batch_to_device(batch, torch.device("cpu"), 0)
    assert isinstance(moved, Batch) and moved.asset_ids == batch.asset_ids
    np.testing.assert_array_equal(moved.images.numpy(), batch.images.numpy())


def test_hydra_config_builds_the_datamodule(tiny_root):
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    conf = str((Path(__file__).parents[2] / "conf").resolve())
    with initialize_config_dir(config_dir=conf, version_base=None):
        cfg = compose(
            config_name="train",
            overrides=[
                "data=synthetic",
                f"paths.data_dir={tiny_root.parent}",
                "data.num_workers=0",
                "data.val_split=test",
            ],
        )
    dm = instantiate(cfg.data)
    dm.setup("fit")
    batch = next(iter(dm.val_dataloader()))
    assert batch.images.shape[-2:] == (64, 64) and batch.target_images.shape[1:] == (8, 3, 64, 64)


def test_surface_points_are_the_assets_own_gaussian_centres_when_asked_for(tiny_root):
    from physgm.gaussians import read_ply

    off = _module(tiny_root)
    off.setup("test")
    assert next(iter(off.test_dataloader())).surface_points is None  # the default: none loaded
    dm = _module(tiny_root, surface_points=64)
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    assert batch.surface_points.shape == (3, 64, 3) and batch.surface_known.all()
    for i, aid in enumerate(batch.asset_ids):
        centres = read_ply(tiny_root / aid / "gaussians.ply", keep_sh=False).means
        # every point is one of the asset's own centres (in the cameras' world frame)
        gap = (batch.surface_points[i][:, None] - centres[None]).norm(dim=-1).amin(dim=1)
        assert gap.max() < 1e-6
