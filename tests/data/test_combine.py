"""`physgm.data.combine`: one root over several data sets, by relative links, feature caches included."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from physgm.data.combine import combine, main
from physgm.data.feature_cache import FeatureStore, build_feature_cache, mobilenet_key
from physgm.data.format import SPLITS, load_asset, read_split
from physgm.errors import UserError
from tests.data.test_feature_cache import CountingEncoder


@pytest.fixture
def two_sets(tiny_root, tmp_path):
    """Two copies of the tiny set under tmp/sets/, the first with a feature cache the second shares
    and one cache of its own."""
    a, b = tmp_path / "sets" / "gen_a", tmp_path / "sets" / "gen_b"
    shutil.copytree(tiny_root, a)
    build_feature_cache(a, mobilenet_key(64, 1.0), log=lambda *_: None)
    shutil.copytree(a, b)
    only_a = a / "features" / "only-in-a"
    only_a.mkdir()
    (only_a / "meta.json").write_text("{}")
    return a, b


def test_the_combined_root_holds_both_sets_and_their_shared_cache(two_sets, tmp_path):
    a, b = two_sets
    out = tmp_path / "sets" / "mix"
    summary = combine(out, [a, b])
    for split in SPLITS:
        own = read_split(a, split)
        assert read_split(out, split) == [f"gen_a--{i}" for i in own] + [f"gen_b--{i}" for i in own]
        assert summary["splits"][split] == 2 * len(own)
    aid = read_split(a, "train")[0]
    linked, source = load_asset(out / f"gen_b--{aid}"), load_asset(b / aid)
    assert linked.id == f"gen_b--{aid}" and linked.physical == source.physical
    assert (out / f"gen_b--{aid}").resolve() == (b / aid).resolve()
    # The shared cache is linked and complete: building it on the combined root computes nothing.
    key = mobilenet_key(64, 1.0)
    assert summary["caches"] == [build_feature_cache(a, key, log=lambda *_: None).name]
    CountingEncoder.calls = 0
    folder = build_feature_cache(out, key, encoder=CountingEncoder(), log=lambda *_: None)
    assert CountingEncoder.calls == 0
    got, want = (
        FeatureStore(folder).load(f"gen_a--{aid}"),
        FeatureStore(a / "features" / folder.name).load(aid),
    )
    assert np.array_equal(got.s8, want.s8)
    assert not (out / "features" / "only-in-a").exists()
    # Relative links: the sets and the root move together.
    moved = shutil.move(tmp_path / "sets", tmp_path / "elsewhere")
    assert load_asset(f"{moved}/mix/gen_a--{aid}").id == f"gen_a--{aid}"
    assert FeatureStore(f"{moved}/mix/features/{folder.name}").load(f"gen_b--{aid}") is not None


def test_bad_requests_are_refused_and_leave_nothing(two_sets, tmp_path, capsys):
    a, b = two_sets
    with pytest.raises(UserError, match="at least two"):
        combine(tmp_path / "one", [a])
    with pytest.raises(UserError, match="must differ"):
        combine(tmp_path / "same", [a, a])
    with pytest.raises(UserError, match="not a data set"):
        combine(tmp_path / "none", [a, tmp_path])
    # A split that lists an asset with no folder: refused after writing began, and nothing is left.
    missing = read_split(b, "test")[0]
    shutil.rmtree(b / missing)
    with pytest.raises(UserError, match=f"lists {missing}"):
        combine(tmp_path / "broken", [a, b])
    assert not list(tmp_path.glob("*broken*")) and not list(tmp_path.glob("one")) + list(
        tmp_path.glob("same")
    )
    (tmp_path / "taken").mkdir()
    assert main([str(tmp_path / "taken"), str(a), str(b)]) == 2
    assert "exists" in capsys.readouterr().err
