"""Preference pairs: selection by distance, the atomic on-disk cache, batching."""

from __future__ import annotations

import json
import math

import pytest
import torch

from physgm.train.pairs import (
    Candidate,
    PairCache,
    PairDataset,
    SceneInputs,
    SceneRecord,
    collate_pairs,
    gather_records,
    policy_fingerprint,
    select_pair,
    settings_hash,
)


def cand(distance, material=9, log10_E=6.0, nu=0.4) -> Candidate:
    return Candidate(material, "rubber", log10_E, nu, distance)


def record(scene="a", round_=0, settings="s1", distances=(0.3, 0.1, 0.5), index=0) -> SceneRecord:
    cands = [cand(d, log10_E=5.0 + i) for i, d in enumerate(distances)]
    w, l, note = select_pair(cands, 0.002)
    return SceneRecord(scene, index, round_, settings, "p1", cands, w, l, 7, note)


@pytest.mark.parametrize(
    "distances,expected",
    [
        ((0.3, 0.1, 0.5), (1, 2)),
        ((0.05, 0.9, 0.2, 0.4), (0, 1)),
        ((0.2, 0.2, 0.7), (0, 2)),  # equal best: the first one wins (deterministic)
        ((0.4, None, 0.1), (2, 1)),  # a failed rollout loses
        ((float("nan"), 0.3, 0.1), (2, 0)),  # so does a non-finite distance
    ],
)
def test_lowest_distance_wins_highest_loses(distances, expected):
    w, l, note = select_pair([cand(d) for d in distances], min_gap=0.002)
    assert (w, l) == expected


def test_ties_and_total_failure_give_no_pair():
    assert select_pair([cand(0.100), cand(0.1005), cand(0.1001)], min_gap=0.002)[:2] == (None, None)
    w, l, note = select_pair([cand(None), cand(None)], min_gap=0.0)
    assert (w, l) == (None, None) and "failed" in note
    # Just above the gap it is a pair.
    assert select_pair([cand(0.1), cand(0.1025)], min_gap=0.002)[:2] == (0, 1)


def src_cand(distance, source, skipped=None) -> Candidate:
    c = cand(distance)
    c.source, c.skipped = source, skipped
    return c


def test_anchor_pairing_rejects_the_policy_draw_and_gives_no_pair_when_it_wins():
    wide, pol = "wide", "policy"
    # the best wide candidate wins against the policy's draw, not against the worst candidate
    assert select_pair([src_cand(0.1, wide), src_cand(0.9, wide), src_cand(0.3, pol)], 0.002, "anchor") == (
        0,
        2,
        "",
    )
    w, l, note = select_pair([src_cand(0.5, wide), src_cand(0.9, wide), src_cand(0.2, pol)], 0.002, "anchor")
    assert (w, l) == (None, None) and note == "the policy's draw won"
    # a failed policy draw loses; a skipped one gives no pair; within min_gap is a tie
    assert select_pair([src_cand(0.5, wide), src_cand(None, pol)], 0.002, "anchor")[:2] == (0, 1)
    assert select_pair([src_cand(0.5, wide), src_cand(0.6, pol, "over budget")], 0.002, "anchor")[:2] == (
        None,
        None,
    )
    assert "tie" in select_pair([src_cand(0.500, wide), src_cand(0.501, pol)], 0.002, "anchor")[2]
    # the first policy draw is the anchor when several are
    assert select_pair([src_cand(0.4, pol), src_cand(0.1, pol), src_cand(0.9, pol)], 0.002, "anchor")[:2] == (
        1,
        0,
    )
    with pytest.raises(ValueError, match="drawn from the policy"):
        select_pair([src_cand(0.1, wide), src_cand(0.2, wide)], 0.002, "anchor")
    with pytest.raises(ValueError, match="unknown pairing"):
        select_pair([src_cand(0.1, wide)], 0.002, "best")


def test_cache_round_trip_and_validation(tmp_path):
    cache = PairCache(tmp_path)
    rec = record()
    path = cache.write(rec)
    assert path == tmp_path / "round_0000" / "a.json"
    back = cache.read(0, "a", "s1", "p1")
    assert back == rec and back.has_pair and back.candidates[back.winner].distance == 0.1
    assert cache.read(1, "a", "s1", "p1") is None  # other round: not in the cache
    assert cache.read(0, "a", "other-settings", "p1") is None  # made with other rollout settings: redo
    assert cache.read(0, "a", "s1", "p2") is None  # drawn from other policy weights: redo
    assert not list((tmp_path / "round_0000").glob(".*"))  # no temporary left behind


def test_half_written_or_incomplete_file_is_never_complete(tmp_path):
    cache = PairCache(tmp_path)
    full = json.dumps(record().to_json())
    cache.path(0, "a").parent.mkdir(parents=True)
    cache.path(0, "a").write_text(full[: len(full) // 2])  # truncated (a non-atomic writer crashed)
    with pytest.warns(UserWarning, match="unreadable"):
        assert cache.read(0, "a", "s1", "p1") is None
    data = record().to_json()
    data["complete"] = False
    cache.path(0, "a").write_text(json.dumps(data))
    assert cache.read(0, "a", "s1", "p1") is None
    # A crashed atomic write leaves only a hidden temporary: never read, and cleaned for that scene.
    tmp = cache.path(0, "b").with_name(".b.json.tmp-123")
    tmp.write_text(full)
    assert cache.read(0, "b", "s1", "p1") is None
    assert cache.clean_temporaries(0, ["b"]) == 1 and not tmp.exists()


def test_policy_fingerprint_follows_the_weights():
    a, b = torch.nn.Linear(3, 2), torch.nn.Linear(3, 2)
    b.load_state_dict(a.state_dict())
    assert policy_fingerprint(a) == policy_fingerprint(b)
    with torch.no_grad():
        b.bias[0] += 1e-7
    assert policy_fingerprint(a) != policy_fingerprint(b)
    # a 0-dim buffer (the domain gate's bias) counts like any other weight
    a.register_buffer("offset", torch.zeros(()))
    before = policy_fingerprint(a)
    a.offset.fill_(0.5)
    assert policy_fingerprint(a) != before


def test_settings_hash_is_stable_and_sensitive():
    a = settings_hash({"k": 3, "sim": {"resolution": 64}})
    assert a == settings_hash({"sim": {"resolution": 64}, "k": 3})
    assert a != settings_hash({"k": 3, "sim": {"resolution": 32}})


def test_gather_on_one_process_sorts_by_scene_index():
    recs = [record("b", index=2), record("a", index=0), record("c", index=1)]
    assert [r.scene for r in gather_records(recs)] == ["a", "c", "b"]


def test_dataset_serves_only_pairs_with_raw_sampled_physics():
    inputs = {
        s: SceneInputs(
            torch.full((2, 3, 8, 8), float(i)),
            torch.ones(2, 1, 8, 8),
            torch.eye(4).expand(2, 4, 4),
            torch.eye(3).expand(2, 3, 3),
        )
        for i, s in enumerate("abc")
    }
    recs = [record("a"), record("b", distances=(0.1, 0.1, 0.1)), record("c", distances=(0.9, None, 0.2))]
    ds = PairDataset(recs, inputs)
    assert len(ds) == 2  # the tie of scene b gives no pair
    batch = collate_pairs([ds[0], ds[1]])
    assert batch.images.shape == (2, 2, 3, 8, 8) and batch.scenes == ["a", "c"]
    assert batch.winner.log10_E.tolist() == [[6.0], [7.0]] and batch.loser.log10_E.tolist() == [[7.0], [6.0]]
    assert batch.winner.material.shape == (2, 1) and batch.winner.material.dtype == torch.int64
    assert batch.distance_winner.tolist() == pytest.approx([0.1, 0.2])
    assert batch.distance_loser[0].item() == pytest.approx(0.5) and math.isinf(batch.distance_loser[1].item())
    assert torch.equal(batch.images[1], inputs["c"].images) and batch.has_pair.tolist() == [True, True]
    # With anchors the tie scene is served too, flagged: no preference, only the KL anchor.
    anchored = PairDataset(recs, inputs, anchors=True)
    assert len(anchored) == 3 and anchored.num_pairs == 2
    batch = collate_pairs([anchored[i] for i in range(3)])
    assert batch.scenes == ["a", "c", "b"] and batch.has_pair.tolist() == [True, True, False]


def _gather_worker(rank: int, world: int, init: str, out: str) -> None:
    torch.distributed.init_process_group("gloo", init_method=init, rank=rank, world_size=world)
    try:
        mine = [
            record(f"s{i}", index=i) for i in range(5) if i % world == rank
        ]  # this rank's share of 5 scenes
        gathered = gather_records(mine)
        with open(f"{out}.{rank}", "w") as f:
            json.dump([r.to_json() for r in gathered], f)
    finally:
        torch.distributed.destroy_process_group()


def test_gather_records_across_two_processes(tmp_path):
    import torch.multiprocessing as mp

    init = f"file://{tmp_path / 'store'}"
    mp.spawn(_gather_worker, args=(2, init, str(tmp_path / "out")), nprocs=2, join=True)
    for rank in (0, 1):
        got = [SceneRecord.from_json(d) for d in json.loads((tmp_path / f"out.{rank}").read_text())]
        assert [r.scene for r in got] == [f"s{i}" for i in range(5)]  # every rank holds every scene, in order
        assert got[3] == record("s3", index=3)
