"""The frozen encoder's feature cache: built once, reused, rebuilt when its key changes."""

from __future__ import annotations

import hashlib
import json
import threading
from dataclasses import asdict

import pytest
import torch

from physgm.data.datamodule import PhysAssetsDataModule
from physgm.data.feature_cache import (
    FeatureStore,
    build_feature_cache,
    cache_dir,
    mobilenet_key,
    stored_view_size,
)
from physgm.data.format import load_asset, read_split
from physgm.data.views import composite_views, ring_views
from physgm.model.cnn_encoder import MobileNetEncoder


class CountingEncoder(MobileNetEncoder):
    calls = 0

    def encode(self, images, classifier_images=None):
        CountingEncoder.calls += 1
        return super().encode(images, classifier_images)


def test_cache_is_reused_and_rebuilt_when_its_key_changes(tiny_copy):
    enc = CountingEncoder()
    key = mobilenet_key(64, 1.0)
    n = len({a for s in ("train", "val", "test", "dpo") for a in read_split(tiny_copy, s)})
    folder = build_feature_cache(tiny_copy, key, encoder=enc, log=lambda *_: None)
    assert CountingEncoder.calls == n and len(list(folder.glob("*.npz"))) == n
    stamp = {p.name: p.stat().st_mtime_ns for p in folder.glob("*.npz")}
    assert build_feature_cache(tiny_copy, key, encoder=enc, log=lambda *_: None) == folder
    assert CountingEncoder.calls == n  # nothing recomputed
    assert stamp == {p.name: p.stat().st_mtime_ns for p in folder.glob("*.npz")}
    for other in (
        mobilenet_key(32, 1.0),
        mobilenet_key(64, 0.5),
        key.__class__(**{**key.__dict__, "weights_sha256": "0" * 64}),
    ):
        assert cache_dir(tiny_copy, other) != folder
        build_feature_cache(tiny_copy, other, encoder=enc, log=lambda *_: None)
    assert CountingEncoder.calls == 4 * n


def test_a_second_builder_waits_and_computes_nothing_the_first_wrote(tiny_copy):
    key = mobilenet_key(64, 1.0)
    holding, waiting = threading.Event(), threading.Event()

    class HeldEncoder(MobileNetEncoder):
        """The first builder's encoder: stalls on its first view until the second builder waits."""

        calls = 0

        def encode(self, images, classifier_images=None):
            if HeldEncoder.calls == 0:
                holding.set()  # called under the lock
                assert waiting.wait(timeout=60), "the second builder never waited for the lock"
            HeldEncoder.calls += 1
            return super().encode(images, classifier_images)

    first = threading.Thread(
        target=build_feature_cache,
        args=(tiny_copy, key, ("train", "val", "test", "dpo"), HeldEncoder()),
        kwargs={"log": lambda *_: None},
    )
    first.start()
    assert holding.wait(timeout=60)
    second_log = []

    def log(msg):
        second_log.append(msg)
        if "waiting" in msg:
            waiting.set()

    before = CountingEncoder.calls
    folder = build_feature_cache(tiny_copy, key, encoder=CountingEncoder(), log=log)
    first.join(timeout=120)
    n = len({a for s in ("train", "val", "test", "dpo") for a in read_split(tiny_copy, s)})
    assert any("another process is building" in m for m in second_log)
    assert HeldEncoder.calls == n and CountingEncoder.calls == before
    assert len(list(folder.glob("*.npz"))) == n


def test_cached_features_are_the_encoder_outputs(tiny_copy):
    enc = MobileNetEncoder()
    store = FeatureStore(
        build_feature_cache(tiny_copy, mobilenet_key(64, 1.0), encoder=enc, log=lambda *_: None)
    )
    aid = read_split(tiny_copy, "train")[0]
    asset = load_asset(tiny_copy / aid)
    views = ring_views(asset.cameras.c2w, 0.0)[:3]
    images, _, _ = composite_views(asset.load_rgba(views), asset.cameras.Ks[views], 64, 1.0)
    expected = enc.encode(images)
    got = store.load(aid, views)
    for a, b in zip(got.levels(), expected.levels(), strict=True):
        torch.testing.assert_close(a.float(), b, rtol=2e-3, atol=2e-3)  # stored as float16
    with pytest.raises(ValueError, match="not cached"):
        store.load(aid, [len(asset.cameras.c2w) - 1])  # a view above the input ring


def test_classifier_reads_the_stored_views_when_they_are_larger_than_the_input(tiny_copy):
    stored = stored_view_size(tiny_copy)
    same = mobilenet_key(stored, 1.0, stored_resolution=stored)
    assert same.classifier_resolution is None
    # keys from before the field existed keep their folder
    old_fields = {k: v for k, v in asdict(same).items() if k != "classifier_resolution"}
    digest = hashlib.sha256(json.dumps(old_fields, sort_keys=True).encode()).hexdigest()[:12]
    assert same.name == f"mobilenet_v2-{stored}px-{digest}"
    small, big = 32, 64  # whatever the set stores, the cache composites views at the key's sizes
    key = mobilenet_key(small, 1.0, stored_resolution=big)
    assert key.classifier_resolution == big and key.name != mobilenet_key(small, 1.0).name
    enc = MobileNetEncoder()
    store = FeatureStore(build_feature_cache(tiny_copy, key, encoder=enc, log=lambda *_: None))
    aid = read_split(tiny_copy, "train")[0]
    asset = load_asset(tiny_copy / aid)
    views = ring_views(asset.cameras.c2w, 0.0)[:2]
    rgba, Ks = asset.load_rgba(views), asset.cameras.Ks[views]
    full, _, _ = composite_views(rgba, Ks, big, 1.0)
    reduced, _, _ = composite_views(rgba, Ks, small, 1.0)
    got = store.load(aid, views)
    assert got.s16.shape[-1] == small // 16  # the pyramid is the input's
    torch.testing.assert_close(got.imagenet_logits.float(), enc.classify(full), rtol=2e-3, atol=2e-2)
    assert (got.imagenet_logits.float() - enc.classify(reduced)).abs().max() > 0.1
    with pytest.raises(ValueError, match="same views"):
        enc.encode(reduced, full[:1])


def test_datamodule_batches_carry_cached_features(tiny_copy):
    dm = PhysAssetsDataModule(
        str(tiny_copy),
        batch_size=2,
        input_resolution=64,
        target_resolution=32,
        feature_cache="mobilenet_v2",
        val_split="train",  # the tiny set's val split may be empty
    )
    dm.setup("fit")
    batch = next(iter(dm.val_dataloader()))
    v = batch.num_views
    assert batch.features is not None and batch.features.s16.shape == (len(batch), v, 96, 4, 4)
    assert batch.features.imagenet_logits.shape == (len(batch), v, 1000)
    with pytest.raises(ValueError, match="input_resolution"):
        PhysAssetsDataModule(str(tiny_copy), feature_cache="mobilenet_v2")


def test_a_datamodule_computes_the_features_of_the_splits_it_serves_only(tiny_copy):
    splits = dict(val_split="test", test_split="train")
    dm = PhysAssetsDataModule(str(tiny_copy), input_resolution=64, feature_cache="mobilenet_v2", **splits)
    dm.setup("validate")
    folder = dm.feature_store(()).folder
    cached = {p.stem for p in folder.glob("*.npz")}
    assert cached == set(read_split(tiny_copy, "test"))  # not the training split's
    dm.setup("test")
    assert {p.stem for p in folder.glob("*.npz")} == cached | set(read_split(tiny_copy, "train"))


def test_an_evaluation_subset_reads_and_caches_evenly_spaced_assets_only(tiny_copy):
    """max_eval_assets: the val and test loaders read that many assets spread over their split lists
    and the cache holds exactly their features; training batches still come from the whole split."""
    train = read_split(tiny_copy, "train")
    assert len(train) >= 6
    dm = PhysAssetsDataModule(
        str(tiny_copy),
        input_resolution=64,
        feature_cache="mobilenet_v2",
        val_split="train",
        test_split="train",
        max_eval_assets=3,
    )
    dm.setup("validate")
    chosen = [a.id for a in dm.dataset("train", False).assets]
    step = len(train) / 3
    assert chosen == [train[int(i * step)] for i in range(3)]
    assert {p.stem for p in dm.feature_store(()).folder.glob("*.npz")} == set(chosen)
    assert len(dm.dataset("train", True)) == len(train)
    with pytest.raises(ValueError, match="max_eval_assets"):
        PhysAssetsDataModule(str(tiny_copy), max_eval_assets=0)
    with pytest.raises(ValueError, match="max_eval_assets"):
        PhysAssetsDataModule(str(tiny_copy), backend="shards", shards_dir="x", max_eval_assets=2)
