"""``PhysAssetsDataModule``: PhysAssets folders (or litdata shards) as typed training batches.

A batch holds V = 1 or 4 input views for every asset in it (never a mix): each example
carries the 4-view input set (views.py) and the collate function keeps the first V, with
V = 1 drawn with probability ``p_single`` per batch. Targets are ``num_targets`` views that
include the inputs. Material labels follow ``physgm.physics.materials.MATERIAL_NAMES``.
"""

from __future__ import annotations

import dataclasses
import warnings
import zlib
from dataclasses import dataclass
from pathlib import Path

import lightning as L
import numpy as np
import torch
from torch import Tensor
from torch.utils.data import DataLoader, Dataset

from physgm.data.feature_cache import (
    CacheKey,
    FeatureStore,
    build_feature_cache,
    mobilenet_key,
    stored_view_size,
)
from physgm.data.format import SPLITS, Asset, AssetError, evenly_spaced, load_asset, read_split
from physgm.data.views import LOAD_ERRORS, Example, ViewConfig, build_example, example_rng
from physgm.model.cnn_encoder import ImageFeatures

CORRUPT_MODES = ("raise", "skip")


@dataclass
class Batch:
    """B assets, V input views, T target views (B V T fixed within a batch)."""

    images: Tensor  # [B, V, 3, H, W] in [0, 1], composited over the background
    masks: Tensor  # [B, V, 1, H, W] alpha in [0, 1]
    c2w: Tensor  # [B, V, 4, 4] OpenCV camera-to-world
    Ks: Tensor  # [B, V, 3, 3] pixel intrinsics at the input resolution
    target_images: Tensor  # [B, T, 3, Ht, Wt]
    target_masks: Tensor  # [B, T, 1, Ht, Wt]
    target_c2w: Tensor  # [B, T, 4, 4]
    target_Ks: Tensor  # [B, T, 3, 3] at the target resolution
    input_index: Tensor  # [B, V] view numbers in each asset
    target_index: Tensor  # [B, T]; target_index[:, :V] == input_index
    material: Tensor  # [B] int64, annotated material class (training label)
    true_material: Tensor  # [B] int64
    log10_E: Tensor  # [B] annotated log10 of E in Pa
    nu: Tensor  # [B] annotated Poisson ratio
    true_log10_E: Tensor  # [B]
    true_nu: Tensor  # [B]
    true_known: Tensor  # [B] bool: False for real assets, whose labels are annotations only
    asset_ids: list[str]
    skipped: list[str]  # corrupt assets dropped while making this batch (on_corrupt="skip")
    features: ImageFeatures | None = None  # [B, V, ...] cached frozen-encoder outputs of the inputs
    surface_points: Tensor | None = None  # [B, S, 3] ground-truth surface points (zeros where unknown)
    surface_known: Tensor | None = None  # [B] bool: the asset has them (synthetic assets)

    @property
    def num_views(self) -> int:
        return self.images.shape[1]

    def __len__(self) -> int:
        return self.images.shape[0]

    def to(self, device: torch.device | str) -> Batch:
        def move(v):
            if isinstance(v, Tensor):
                return v.to(device)
            return v.map(lambda t: t.to(device)) if isinstance(v, ImageFeatures) else v

        return Batch(**{f.name: move(getattr(self, f.name)) for f in dataclasses.fields(self)})


class Collate:
    """Stack examples, keeping the first V in {1, 4} input views for the whole batch.

    Training draws V from torch's RNG (seeded per worker by the DataLoader, so
    ``seed_everything`` makes it reproducible); evaluation derives V from the asset ids so a
    validation batch always has the same V.
    """

    def __init__(self, p_single: float, deterministic: bool):
        if not 0.0 <= p_single <= 1.0:
            raise ValueError(f"p_single must be in [0, 1], got {p_single}")
        self.p_single, self.deterministic = p_single, deterministic

    def num_views(self, ids: list[str]) -> int:
        u = zlib.crc32("|".join(ids).encode()) / 2**32 if self.deterministic else float(torch.rand(()))
        return 1 if u < self.p_single else 4

    def __call__(self, items: list[Example | tuple[Example | None, list[str]] | None]) -> Batch:
        examples, skipped = [], []
        for it in items:
            ex, sk = it if isinstance(it, tuple) else (it, [])
            skipped += sk
            if ex is not None:
                examples.append(ex)
        if not examples:
            raise AssetError(f"every asset of a batch was corrupt and skipped: {skipped}")
        v = self.num_views([e.id for e in examples])

        def stack(name: str, n: int | None = None) -> Tensor:
            return torch.stack([getattr(e, name)[:n] if n else getattr(e, name) for e in examples])

        def vec(name: str, dtype: torch.dtype) -> Tensor:
            return torch.tensor([getattr(e, name) for e in examples], dtype=dtype)

        return Batch(
            images=stack("input_images", v),
            masks=stack("input_masks", v),
            c2w=stack("input_c2w", v),
            Ks=stack("input_Ks", v),
            input_index=stack("input_index", v),
            target_images=stack("target_images"),
            target_masks=stack("target_masks"),
            target_c2w=stack("target_c2w"),
            target_Ks=stack("target_Ks"),
            target_index=stack("target_index"),
            material=vec("material", torch.int64),
            true_material=vec("true_material", torch.int64),
            log10_E=vec("log10_E", torch.float32),
            nu=vec("nu", torch.float32),
            true_log10_E=vec("true_log10_E", torch.float32),
            true_nu=vec("true_nu", torch.float32),
            true_known=vec("true_known", torch.bool),
            asset_ids=[e.id for e in examples],
            skipped=skipped,
            features=_stack_features([e.input_features for e in examples], v),
            **_stack_surface([e.surface_points for e in examples]),
        )


def _stack_surface(items: list[Tensor | None]) -> dict[str, Tensor | None]:
    """surface_points [B, S, 3] (zeros for assets without them) and surface_known [B], or Nones."""
    known = [p is not None for p in items]
    if not any(known):
        return {"surface_points": None, "surface_known": None}
    shape = next(p for p in items if p is not None).shape
    points = torch.stack([p if p is not None else torch.zeros(shape) for p in items])
    return {"surface_points": points, "surface_known": torch.tensor(known)}


def _stack_features(items: list[ImageFeatures | None], v: int) -> ImageFeatures | None:
    if all(f is None for f in items):
        return None
    if any(f is None for f in items):
        raise ValueError(
            "some examples of a batch have cached features and others not; rebuild the feature cache"
        )
    return ImageFeatures.stack([f.map(lambda t: t[:v]) for f in items])


@dataclass
class FolderRecord:
    """An ``Asset`` seen through the ``AssetRecord`` protocol."""

    asset: Asset

    def __post_init__(self) -> None:
        a = self.asset
        self.id, self.c2w, self.Ks = a.id, a.cameras.c2w, a.cameras.Ks
        self.width, self.height, self.physical = a.cameras.width, a.cameras.height, a.physical

    def load_rgba(self, indices: list[int]) -> np.ndarray:
        return self.asset.load_rgba(indices)

    def load_surface(self) -> np.ndarray | None:
        if self.asset.gaussians_path is None:
            return None
        return self.asset.load_gaussians(keep_sh=False).means.numpy()


class FolderDataset(Dataset):
    """Assets of one split read from a PhysAssets folder (``max_assets``: at most that many, evenly
    spaced over the split list)."""

    def __init__(
        self,
        root: str | Path,
        split: str,
        views: ViewConfig,
        deterministic: bool,
        on_corrupt: str = "raise",
        seed: int = 0,
        features: FeatureStore | None = None,
        max_assets: int | None = None,
    ):
        if on_corrupt not in CORRUPT_MODES:
            raise ValueError(f"on_corrupt must be one of {CORRUPT_MODES}, got {on_corrupt!r}")
        self.root, self.split, self.views = Path(root), split, views
        self.deterministic, self.on_corrupt, self.seed = deterministic, on_corrupt, seed
        self.features = features
        self.assets: list[Asset] = []
        self.skipped: dict[str, str] = {}  # found malformed while scanning (on_corrupt="skip")
        for aid in evenly_spaced(read_split(self.root, split), max_assets):
            try:
                self.assets.append(load_asset(self.root / aid))
            except AssetError as err:
                if on_corrupt == "raise":
                    raise
                self.skipped[aid] = str(err)
        if self.skipped:
            warnings.warn(
                f"{split}: skipped {len(self.skipped)} malformed asset(s): {sorted(self.skipped)[:10]}",
                stacklevel=2,
            )
        if not self.assets:
            raise ValueError(f"split {split!r} of {self.root} has no usable assets")

    def __len__(self) -> int:
        return len(self.assets)

    def __getitem__(self, index: int) -> tuple[Example, list[str]]:
        skipped: list[str] = []
        # A view can still be unreadable at load time; with "skip" try the next assets.
        for k in range(min(len(self.assets), 8)):
            asset = self.assets[(index + k) % len(self.assets)]
            try:
                rng = example_rng(asset.id, self.deterministic, self.seed)
                return build_example(FolderRecord(asset), self.views, rng, self.features), skipped
            except LOAD_ERRORS as err:
                if self.on_corrupt == "raise":
                    raise AssetError(f"asset {asset.id} ({asset.path}) could not be loaded: {err}") from err
                skipped.append(asset.id)
        raise AssetError(
            f"{len(skipped)} consecutive corrupt assets near index {index} of split {self.split}: {skipped}"
        )


class PhysAssetsDataModule(L.LightningDataModule):
    """Train/val/test/dpo loaders over a PhysAssets folder or its litdata shards.

    Args:
        root: data set folder (asset folders + splits/).
        backend: "folder" reads the folders; "shards" streams ``<shards_dir>/<split>/`` written
            by ``python -m physgm.data.shards`` (for many nodes; local path or cloud URL).
        batch_size, num_workers, pin_memory: DataLoader settings (batch_size per device).
        p_single: chance that a training batch has 1 input view instead of 4.
        eval_p_single: same for val/test/dpo batches (fixed per batch).
        num_targets: target views per asset (includes the inputs).
        input_resolution, target_resolution: square sizes in px (None: stored size).
        background: grey level behind the object (1 = white, like the renders).
        random_azimuth: training only, start the input set at a random azimuth.
        on_corrupt: "raise" stops naming the asset; "skip" drops it and counts it.
        train_split, val_split, test_split: which split files feed each stage (the DPO
            stage trains on "dpo").
        seed: seed for the fixed evaluation views.
        feature_cache: ``"mobilenet_v2"`` reads the frozen encoder's features of the input views
            from ``<root>/features/`` (``physgm.data.feature_cache``, built on first use) so that
            training skips the encoder; None computes them in every step.
        max_eval_assets: the val, test and dpo loaders read at most this many assets of their
            split, evenly spaced over its list (a quicker score, or a score on a subset of the
            training split); None reads them all. Training batches always come from the whole split.
    """

    def __init__(
        self,
        root: str,
        backend: str = "folder",
        shards_dir: str | None = None,
        batch_size: int = 4,
        num_workers: int = 0,
        pin_memory: bool = False,
        p_single: float = 0.5,
        eval_p_single: float = 0.5,
        num_targets: int = 8,
        input_resolution: int | None = None,
        target_resolution: int | None = None,
        background: float = 1.0,
        random_azimuth: bool = False,
        surface_points: int = 0,
        on_corrupt: str = "raise",
        train_split: str = "train",
        val_split: str = "val",
        test_split: str = "test",
        seed: int = 0,
        feature_cache: str | None = None,
        max_eval_assets: int | None = None,
    ):
        super().__init__()
        if feature_cache not in (None, "mobilenet_v2"):
            raise ValueError(f"feature_cache must be null or 'mobilenet_v2', got {feature_cache!r}")
        if feature_cache and backend != "folder":
            raise ValueError(
                "feature_cache works with backend='folder' (the shards do not carry features yet)"
            )
        if feature_cache and not input_resolution:
            raise ValueError("feature_cache needs input_resolution: the cache is keyed by it")
        if max_eval_assets is not None and (max_eval_assets < 1 or backend != "folder"):
            raise ValueError(
                f"max_eval_assets must be null or at least 1 with backend='folder', got {max_eval_assets} "
                f"with backend={backend!r}"
            )
        if backend not in ("folder", "shards"):
            raise ValueError(f"backend must be 'folder' or 'shards', got {backend!r}")
        if backend == "shards" and not shards_dir:
            raise ValueError("backend='shards' needs shards_dir (written by `python -m physgm.data.shards`)")
        for s in (train_split, val_split, test_split):
            if s not in SPLITS:
                raise ValueError(f"unknown split {s!r}; choose from {SPLITS}")
        if on_corrupt not in CORRUPT_MODES:
            raise ValueError(f"on_corrupt must be one of {CORRUPT_MODES}, got {on_corrupt!r}")
        self.save_hyperparameters()
        self.hp = self.hparams
        self.datasets: dict[str, Dataset] = {}
        self._features: FeatureStore | None = None  # built on first use (feature_store)
        self._feature_key: CacheKey | None = None  # the cache's key, read from the data on first use

    def view_config(self, train: bool) -> ViewConfig:
        return ViewConfig(
            self.hp.num_targets,
            self.hp.input_resolution,
            self.hp.target_resolution,
            self.hp.background,
            self.hp.random_azimuth and train,
            surface_points=self.hp.surface_points,
        )

    def dataset(self, split: str, train: bool) -> Dataset:
        """The dataset of ``split`` (built once)."""
        key = f"{split}:{train}"
        if key not in self.datasets:
            if self.hp.backend == "folder":
                subset = None if train else self.hp.max_eval_assets
                self.datasets[key] = FolderDataset(
                    self.hp.root,
                    split,
                    self.view_config(train),
                    not train,
                    self.hp.on_corrupt,
                    self.hp.seed,
                    self.feature_store((split,), subset),
                    subset,
                )
            else:
                from physgm.data.shards import ShardDataset

                self.datasets[key] = ShardDataset(
                    f"{str(self.hp.shards_dir).rstrip('/')}/{split}",
                    self.view_config(train),
                    deterministic=not train,
                    shuffle=train,
                    on_corrupt=self.hp.on_corrupt,
                    seed=self.hp.seed,
                )
        return self.datasets[key]

    def feature_store(
        self, splits: tuple[str, ...] = SPLITS, max_assets: int | None = None
    ) -> FeatureStore | None:
        """The frozen encoder's cache of this data set, with the features of ``splits`` (or of the
        evenly spaced ``max_assets`` of each) built where missing (a training run does not compute
        its test split's)."""
        if not self.hp.feature_cache:
            return None
        if self._feature_key is None:
            stored = stored_view_size(self.hp.root)
            self._feature_key = mobilenet_key(
                self.hp.input_resolution, self.hp.background, stored_resolution=stored
            )
        folder = build_feature_cache(self.hp.root, self._feature_key, splits, max_assets=max_assets)
        if self._features is None:
            self._features = FeatureStore(folder)
        return self._features

    def setup(self, stage: str | None = None) -> None:
        if stage in (None, "fit"):
            self.dataset(self.hp.train_split, True)
            self.dataset(self.hp.val_split, False)
        if stage in (None, "validate"):
            self.dataset(self.hp.val_split, False)
        if stage in (None, "test"):
            self.dataset(self.hp.test_split, False)

    @property
    def skipped_assets(self) -> dict[str, str]:
        """Assets found malformed while scanning the folders (on_corrupt="skip")."""
        out: dict[str, str] = {}
        for ds in self.datasets.values():
            out.update(getattr(ds, "skipped", {}))
        return out

    def _loader(self, split: str, train: bool) -> DataLoader:
        ds = self.dataset(split, train)
        collate = Collate(self.hp.p_single if train else self.hp.eval_p_single, deterministic=not train)
        kwargs = dict(
            batch_size=self.hp.batch_size,
            num_workers=self.hp.num_workers,
            collate_fn=collate,
            pin_memory=self.hp.pin_memory,
            persistent_workers=self.hp.num_workers > 0,
        )
        if self.hp.backend == "shards":
            from litdata import StreamingDataLoader

            return StreamingDataLoader(ds, drop_last=train, **kwargs)
        return DataLoader(ds, shuffle=train, drop_last=train and len(ds) >= self.hp.batch_size, **kwargs)

    def train_dataloader(self) -> DataLoader:
        return self._loader(self.hp.train_split, True)

    def val_dataloader(self) -> DataLoader:
        return self._loader(self.hp.val_split, False)

    def test_dataloader(self) -> DataLoader:
        return self._loader(self.hp.test_split, False)

    def dpo_dataloader(self) -> DataLoader:
        """Assets with reference videos (the DPO split), in a fixed order."""
        return self._loader("dpo", False)

    def transfer_batch_to_device(self, batch: Batch, device: torch.device, dataloader_idx: int) -> Batch:
        return batch.to(device)
