"""litdata shards: writing a split and reading back exactly the folder samples."""

from __future__ import annotations

import pytest
import torch

from physgm.data.datamodule import FolderDataset, PhysAssetsDataModule
from physgm.data.shards import ShardDataset, write_shards
from physgm.data.views import ViewConfig


@pytest.fixture(scope="module")
def shard_dir(tiny_root, tmp_path_factory):
    out = tmp_path_factory.mktemp("shards")
    counts = write_shards(tiny_root, out, splits=("train", "test"), chunk_bytes="256KB")
    assert counts["train"] > 10
    return out


def test_shard_round_trip_gives_the_same_examples(tiny_root, shard_dir):
    out = shard_dir
    views = ViewConfig(input_resolution=16)
    folder = FolderDataset(tiny_root, "train", views, deterministic=True)
    shards = ShardDataset(str(out / "train"), views, deterministic=True)
    assert len(shards) == len(folder)
    from_shards = {ex.id: ex for ex, _ in (shards[i] for i in range(len(shards)))}
    assert set(from_shards) == {a.id for a in folder.assets}
    for i in range(len(folder)):
        ex, _ = folder[i]
        other = from_shards[ex.id]
        for name in (
            "input_images",
            "input_masks",
            "input_c2w",
            "input_Ks",
            "input_index",
            "target_images",
            "target_masks",
            "target_c2w",
            "target_Ks",
            "target_index",
        ):
            assert torch.equal(getattr(ex, name), getattr(other, name)), (ex.id, name)
        assert (ex.material, ex.true_material, ex.log10_E, ex.nu, ex.true_log10_E, ex.true_nu) == (
            other.material,
            other.true_material,
            other.log10_E,
            other.nu,
            other.true_log10_E,
            other.true_nu,
        )


def test_datamodule_streams_shards(tiny_root, shard_dir):
    out = shard_dir
    dm = PhysAssetsDataModule(
        str(tiny_root),
        backend="shards",
        shards_dir=str(out),
        batch_size=4,
        p_single=0.0,
        val_split="test",
        input_resolution=16,
    )
    dm.setup("fit")
    ids = []
    for batch in dm.train_dataloader():
        assert batch.images.shape == (4, 4, 3, 16, 16) and batch.target_images.shape == (4, 8, 3, 32, 32)
        ids += batch.asset_ids
    train = (tiny_root / "splits" / "train.txt").read_text().split()
    assert len(ids) == 4 * (len(train) // 4) and set(ids) <= set(train) and len(set(ids)) == len(ids)
