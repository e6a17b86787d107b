"""Preference pairs for the DPO stage: selection by trajectory distance, an on-disk cache, batches.

One JSON file per scene and refresh round, ``<cache_dir>/round_<r>/<scene_id>.json``, holds the
K sampled candidates (raw sampled physics, as the policy's ``log_prob`` needs them), their
trajectory distances to the reference video and which one won and lost. A file is written
to a hidden temporary name and renamed in one step, so a crash never leaves a half-written
file under the final name; a file that does not parse, is not marked complete, or was made
for another round or other rollout settings is treated as missing and redone.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch
from torch import Tensor
from torch.utils.data import Dataset

from physgm.model.posterior import PhysicsSample

CACHE_VERSION = 2  # 2: candidates carry their proposal, budget fallback and skip reason


@dataclass
class Candidate:
    """One sampled physics and how well its simulation matched the reference video."""

    material: int  # class index into physgm.physics.materials.MATERIAL_NAMES
    material_name: str
    log10_E: float  # as sampled (unclipped), log10 Pa
    nu: float  # as sampled (unclipped)
    distance: float | None  # trajectory distance (bounding-box units); None when the rollout failed
    seconds: float = 0.0  # wall-clock time of simulate + render + score
    mode: str = ""  # "rigid" or "mpm", from the simulation plan
    error: str | None = None  # why the rollout failed
    source: str = "policy"  # the proposal that drew it ("policy" or "wide", physgm.train.proposal)
    skipped: str | None = None  # why the time budget skipped or cut it (then it is neither winner nor loser)
    fallback: int = -1  # -1: simulated as planned; i: the budget's i-th cheaper planner setting
    predicted_error_px: float = 0.0  # the plan's predicted error against full-stiffness MPM, pixels
    terms: dict[str, float] = field(default_factory=dict)  # the score's parts (physgm.metrics.clip_score)

    @property
    def score(self) -> float:
        """Distance for ranking; failed or non-finite rollouts rank last."""
        d = self.distance
        return d if d is not None and math.isfinite(d) else math.inf


@dataclass
class SceneRecord:
    """The rollouts of one scene in one refresh round and the pair they gave (if any)."""

    scene: str  # asset id
    scene_index: int  # position in the DPO split (decides the DDP rank that simulates it)
    round: int
    settings: str  # hash of the rollout settings the record was made with
    policy: str  # fingerprint of the policy weights the candidates were drawn from
    candidates: list[Candidate]
    winner: int | None  # index into candidates; None when no usable pair (tie / failures)
    loser: int | None
    global_step: int = 0  # policy step the candidates were drawn at
    note: str = ""  # why there is no pair
    complete: bool = True
    version: int = CACHE_VERSION

    @property
    def has_pair(self) -> bool:
        return self.winner is not None and self.loser is not None

    def to_json(self) -> dict:
        return asdict(self)

    @classmethod
    def from_json(cls, data: dict) -> SceneRecord:
        data = dict(data)
        data["candidates"] = [Candidate(**c) for c in data["candidates"]]
        return cls(**data)

    def pair_again(self, min_gap: float, pairing: str) -> None:
        """Choose the pair from the same candidates by ``pairing`` (a record may come from another rule)."""
        self.winner, self.loser, self.note = select_pair(self.candidates, min_gap, pairing)


PAIRINGS = ("extremes", "anchor")  # how select_pair picks the rejected candidate (``stage.rollout.pairing``)


def policy_draw(candidates: list[Candidate]) -> int | None:
    """Index of the first candidate drawn from the policy (the anchor pairs' loser), or None."""
    return next((i for i, c in enumerate(candidates) if c.source == "policy"), None)


def select_pair(
    candidates: list[Candidate], min_gap: float, pairing: str = "extremes"
) -> tuple[int | None, int | None, str]:
    """(winner, loser, note): the lowest distance wins; ``pairing`` says which candidate loses.

    - ``extremes`` (the paper's): the highest distance loses.
    - ``anchor``: the policy's own draw (the first candidate whose source is "policy") loses, and
      there is no pair when it wins. For a Gaussian policy the DPO gradient on the mean points
      from the loser to the winner wherever the mean is, so only a loser at the policy's own
      draw makes it point from the policy towards the winner; best against worst pointed the
      right way in about half the pairs once the policy had moved (docs/model.md).

    No pair when fewer than two candidates have finite distances, or when the winner and the
    loser are less than ``min_gap`` apart (a tie, e.g. stiff bodies that all move rigidly):
    such pairs carry no preference, only tracker noise. A failed rollout loses against any
    finished one, so physics that cannot be simulated is pushed away. A candidate the time
    budget skipped or cut says nothing about the physics and takes no part.
    """
    if pairing not in PAIRINGS:
        raise ValueError(f"unknown pairing {pairing!r}; choose one of {', '.join(PAIRINGS)}")
    scores = [math.nan if c.skipped else c.score for c in candidates]
    finite = [i for i, s in enumerate(scores) if math.isfinite(s)]
    if not finite:
        return None, None, "every rollout failed"
    winner = min(finite, key=lambda i: (scores[i], i))
    failed = [i for i, s in enumerate(scores) if math.isinf(s)]
    if pairing == "anchor":
        anchor = policy_draw(candidates)
        if anchor is None:
            raise ValueError("pairing 'anchor' needs a candidate drawn from the policy; lower wide_fraction")
        if candidates[anchor].skipped:
            return None, None, "the policy's draw was skipped over the time budget"
        if anchor == winner:
            return None, None, "the policy's draw won"
        if math.isinf(scores[anchor]):
            return winner, anchor, "loser failed to simulate"
        loser = anchor
    elif failed:
        return winner, failed[0], "loser failed to simulate"
    else:
        loser = max(finite, key=lambda i: (scores[i], -i))
    if loser == winner:
        return None, None, "fewer than two candidates within the time budget"
    if scores[loser] - scores[winner] < min_gap:
        return None, None, f"tie: distances within {min_gap}"
    return winner, loser, ""


def policy_fingerprint(model: torch.nn.Module) -> str:
    """Short hash of a model's weights: a cached round is reused only for the policy that made it."""
    h = hashlib.sha1()
    for name, p in sorted(model.state_dict().items()):
        h.update(name.encode())
        flat = p.detach().cpu().reshape(-1).contiguous()  # a 0-dim buffer (the gate's bias) as one element
        h.update(flat.view(torch.uint8).numpy().tobytes() if p.numel() else b"")
    return h.hexdigest()[:16]


def settings_hash(settings: dict) -> str:
    """Short stable hash of the settings that change what a rollout produces."""
    text = json.dumps(settings, sort_keys=True, default=str)
    return hashlib.sha1(text.encode()).hexdigest()[:12]


class PairCache:
    """Scene records on disk, one file per scene and round, written atomically."""

    def __init__(self, root: str | os.PathLike) -> None:
        self.root = Path(root)

    def path(self, round_: int, scene: str) -> Path:
        return self.root / f"round_{round_:04d}" / f"{scene}.json"

    def write(self, record: SceneRecord) -> Path:
        """Write one record: temporary file, fsync, then an atomic rename onto the final name."""
        final = self.path(record.round, record.scene)
        final.parent.mkdir(parents=True, exist_ok=True)
        tmp = final.with_name(f".{final.name}.tmp-{os.getpid()}")
        with open(tmp, "w") as f:
            json.dump(record.to_json(), f, indent=1, sort_keys=True)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, final)
        return final

    def read(self, round_: int, scene: str, settings: str, policy: str) -> SceneRecord | None:
        """The finished record of ``scene`` in ``round_`` with ``settings`` from ``policy``, else None."""
        path = self.path(round_, scene)
        if not path.is_file():
            return None
        try:
            record = SceneRecord.from_json(json.loads(path.read_text()))
        except (OSError, ValueError, TypeError, KeyError) as err:
            warnings.warn(
                f"ignoring unreadable pair cache file {path} ({err}); the scene is rolled out again",
                stacklevel=2,
            )
            return None
        ok = (
            record.complete
            and record.version == CACHE_VERSION
            and record.round == round_
            and record.scene == scene
            and record.settings == settings
            and record.policy == policy
        )
        return record if ok else None

    def write_summary(self, round_: int, stats: dict) -> Path:
        """``round_<r>/_summary.json`` (atomic, like the records)."""
        final = self.root / f"round_{round_:04d}" / "_summary.json"
        final.parent.mkdir(parents=True, exist_ok=True)
        tmp = final.with_name(f"._summary.json.tmp-{os.getpid()}")
        tmp.write_text(json.dumps(stats, indent=1, sort_keys=True))
        os.replace(tmp, final)
        return final

    def clean_temporaries(self, round_: int, scenes: list[str]) -> int:
        """Remove temporary files an interrupted write left for ``scenes``; returns how many.

        Only the caller's own scenes: under DDP another rank may be writing its files right now.
        """
        folder = self.root / f"round_{round_:04d}"
        stale = [p for s in scenes for p in folder.glob(f".{s}.json.tmp-*")] if folder.is_dir() else []
        for p in stale:
            p.unlink(missing_ok=True)
        return len(stale)


def round_stats(records: list[SceneRecord]) -> dict[str, float]:
    """What a round of rollouts gave: scenes, pairs, failures and mean distances."""
    pairs = [r for r in records if r.has_pair]
    dist = [c.distance for r in records for c in r.candidates if c.distance is not None]
    losers = [r.candidates[r.loser].score for r in pairs if math.isfinite(r.candidates[r.loser].score)]

    def mean(x: list[float]) -> float:
        return float(sum(x) / len(x)) if x else float("nan")

    return {
        "rollout/scenes": float(len(records)),
        "rollout/pairs": float(len(pairs)),
        "rollout/failed": float(
            sum(c.distance is None and not c.skipped for r in records for c in r.candidates)
        ),
        "rollout/skipped": float(sum(bool(c.skipped) for r in records for c in r.candidates)),
        "rollout/distance_mean": mean(dist),
        "rollout/distance_winner": mean([r.candidates[r.winner].score for r in pairs]),
        "rollout/distance_loser": mean(losers),
    }


def gather_records(records: list[SceneRecord]) -> list[SceneRecord]:
    """All ranks' records on every rank (DDP), sorted by scene index; a no-op on one process."""
    if (
        torch.distributed.is_available()
        and torch.distributed.is_initialized()
        and torch.distributed.get_world_size() > 1
    ):
        parts: list[list[dict] | None] = [None] * torch.distributed.get_world_size()
        torch.distributed.all_gather_object(parts, [r.to_json() for r in records])
        records = [SceneRecord.from_json(d) for part in parts for d in (part or [])]
    return sorted(records, key=lambda r: r.scene_index)


# -- training batches ------------------------------------------------------------------------


@dataclass
class SceneInputs:
    """The posed input views of one scene, as the model sees them."""

    images: Tensor  # [V, 3, H, W] in [0, 1]
    masks: Tensor  # [V, 1, H, W]
    c2w: Tensor  # [V, 4, 4]
    Ks: Tensor  # [V, 3, 3]


@dataclass
class DPOBatch:
    """B preference pairs with their scenes' inputs."""

    images: Tensor  # [B, V, 3, H, W]
    masks: Tensor  # [B, V, 1, H, W]
    c2w: Tensor  # [B, V, 4, 4]
    Ks: Tensor  # [B, V, 3, 3]
    winner: PhysicsSample  # [B, 1] sampled physics that tracked the reference best
    loser: PhysicsSample  # [B, 1] worst
    distance_winner: Tensor  # [B]
    distance_loser: Tensor  # [B] (inf when the loser failed to simulate)
    has_pair: Tensor  # [B] bool; False: a tie scene served only as a KL anchor (winner = loser = a candidate)
    scenes: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return self.images.shape[0]

    def to(self, device: torch.device | str) -> DPOBatch:
        def move(s: PhysicsSample) -> PhysicsSample:
            return PhysicsSample(s.material.to(device), s.log10_E.to(device), s.nu.to(device))

        return DPOBatch(
            self.images.to(device),
            self.masks.to(device),
            self.c2w.to(device),
            self.Ks.to(device),
            move(self.winner),
            move(self.loser),
            self.distance_winner.to(device),
            self.distance_loser.to(device),
            self.has_pair.to(device),
            self.scenes,
        )


class PairDataset(Dataset):
    """(scene inputs, winner physics, loser physics) for every record that has a pair.

    With ``anchors`` the scenes without a pair (ties: e.g. stiff objects whose candidates all
    move alike) are served too, flagged ``has_pair=False``: they carry no preference, but a KL
    penalty on them keeps the shared physics head from drifting where the videos say nothing.
    """

    def __init__(
        self, records: list[SceneRecord], inputs: dict[str, SceneInputs], anchors: bool = False
    ) -> None:
        self.items = [r for r in records if r.has_pair] + [
            r for r in records if anchors and not r.has_pair and r.candidates
        ]
        missing = sorted({r.scene for r in self.items} - set(inputs))
        if missing:
            raise KeyError(f"pair records name scenes without loaded inputs: {missing[:5]}")
        self.inputs = inputs

    def __len__(self) -> int:
        return len(self.items)

    @property
    def num_pairs(self) -> int:
        return sum(r.has_pair for r in self.items)

    def __getitem__(self, index: int) -> tuple[SceneInputs, Candidate, Candidate, str, bool]:
        r = self.items[index]
        if not r.has_pair:
            return self.inputs[r.scene], r.candidates[0], r.candidates[0], r.scene, False
        return self.inputs[r.scene], r.candidates[r.winner], r.candidates[r.loser], r.scene, True


def collate_pairs(items: list[tuple[SceneInputs, Candidate, Candidate, str, bool]]) -> DPOBatch:
    """Stack pairs into a ``DPOBatch`` (every scene must have the same V, H, W)."""

    def sample(cands: list[Candidate]) -> PhysicsSample:
        return PhysicsSample(
            torch.tensor([[c.material] for c in cands], dtype=torch.int64),
            torch.tensor([[c.log10_E] for c in cands], dtype=torch.float32),
            torch.tensor([[c.nu] for c in cands], dtype=torch.float32),
        )

    inputs, wins, losses, scenes, has_pair = zip(*items, strict=True)
    return DPOBatch(
        images=torch.stack([i.images for i in inputs]),
        masks=torch.stack([i.masks for i in inputs]),
        c2w=torch.stack([i.c2w for i in inputs]),
        Ks=torch.stack([i.Ks for i in inputs]),
        winner=sample(list(wins)),
        loser=sample(list(losses)),
        distance_winner=torch.tensor([c.score for c in wins], dtype=torch.float32),
        distance_loser=torch.tensor([c.score for c in losses], dtype=torch.float32),
        has_pair=torch.tensor(has_pair, dtype=torch.bool),
        scenes=list(scenes),
    )
