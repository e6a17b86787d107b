"""``python -m physgm.bench material-probe``: how much the views alone say about the material.

Trains a small CNN with a single task, the true material of an asset from one of its views, on
the train split of a data set (every view of every asset, flipped at random), and reports its
accuracy on the test split with the evaluation's input views: view 1 alone, and views 1-4 with
their log-probabilities averaged (``physgm.data.views.select_views``, as in
``python -m physgm.train.evaluate``), and the same accuracies on its own training assets (far
above the test accuracy: the probe is limited by data rather than steps). ``--test-data`` takes
the test split from another folder, e.g. a smaller set whose assets a larger one contains.

The probe does no 3D reconstruction and no physics, so its accuracy is a reference point for
PhysGM's material accuracy on the same data and resolution: what a from-scratch image model
reaches in the same budget. Prints one JSON object.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from physgm.data.format import load_asset, read_split
from physgm.data.views import ViewConfig, select_views
from physgm.physics.materials import MATERIAL_NAMES


def load_split(root: str, split: str, eval_views: bool) -> tuple[Tensor, Tensor, list[str]]:
    """Views [A, V, 4, H, W] (RGB over white, then alpha) and true material indices [A].

    ``eval_views``: only the 4 evaluation input views (view 1 first); otherwise every view.
    """
    images, labels, ids = [], [], read_split(root, split)
    if not ids:
        raise ValueError(f"split {split!r} of {root} lists no assets")
    for asset_id in ids:
        asset = load_asset(f"{root}/{asset_id}")
        views = select_views(asset.cameras.c2w, ViewConfig(), None)[0] if eval_views else None
        rgba = asset.load_rgba(views)  # [V, H, W, 4]
        rgb = rgba[..., :3] * rgba[..., 3:] + (1.0 - rgba[..., 3:])
        images.append(np.concatenate([rgb, rgba[..., 3:]], axis=-1).transpose(0, 3, 1, 2))
        labels.append(MATERIAL_NAMES.index(asset.physical.material))
    sizes = {im.shape for im in images}
    if len(sizes) > 1:
        raise ValueError(f"split {split!r} mixes view counts or sizes {sorted(sizes)}; the probe needs one")
    return torch.from_numpy(np.stack(images)), torch.tensor(labels), ids


def probe_net(num_classes: int, width: int = 32) -> nn.Sequential:
    """Four conv blocks (two 3x3 convs, batch norm, 2x2 max pool), global pooling, a linear layer."""

    def block(c_in: int, c_out: int) -> nn.Sequential:
        return nn.Sequential(
            nn.Conv2d(c_in, c_out, 3, padding=1),
            nn.BatchNorm2d(c_out),
            nn.ReLU(),
            nn.Conv2d(c_out, c_out, 3, padding=1),
            nn.BatchNorm2d(c_out),
            nn.ReLU(),
            nn.MaxPool2d(2),
        )

    chans = [4, width, 2 * width, 4 * width, 4 * width]
    blocks = [block(a, b) for a, b in zip(chans[:-1], chans[1:], strict=True)]
    return nn.Sequential(
        *blocks, nn.AdaptiveAvgPool2d(1), nn.Flatten(), nn.Dropout(0.3), nn.Linear(chans[-1], num_classes)
    )


@torch.no_grad()
def accuracy(net: nn.Module, images: Tensor, labels: Tensor) -> tuple[float, float]:
    """(accuracy from view 1, accuracy from views 1-4 with averaged log-probabilities)."""
    net.eval()
    # In chunks of assets: 3195 training assets in one batch are 12780 images, 6.7 GB for every
    # 32-channel activation of the first block alone.
    logp = torch.cat(
        [net(chunk.flatten(0, 1)).log_softmax(-1).view(*chunk.shape[:2], -1) for chunk in images.split(128)]
    )
    net.train()
    one = (logp[:, 0].argmax(-1) == labels).float().mean().item()
    four = (logp.mean(1).argmax(-1) == labels).float().mean().item()
    return one, four


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(
        prog="python -m physgm.bench material-probe", description=__doc__.splitlines()[0]
    )
    p.add_argument(
        "--data", default="data/synthetic_tiny", help="PhysAssets folder with splits/train.txt and test.txt"
    )
    p.add_argument(
        "--test-data", default=None, help="take the test split from this folder instead (default: --data)"
    )
    p.add_argument("--seconds", type=float, default=900.0, help="training budget (wall clock)")
    p.add_argument(
        "--steps", type=int, default=None, help="also stop after this many steps (load cannot move it)"
    )
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--lr", type=float, default=2e-3)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    if not args.seconds > 0 or args.batch < 2 or (args.steps is not None and args.steps < 1):
        raise SystemExit(
            f"--seconds must be > 0, --batch >= 2 and --steps >= 1, "
            f"got {args.seconds}, {args.batch} and {args.steps}"
        )
    max_steps = args.steps if args.steps is not None else float("inf")
    torch.manual_seed(args.seed)
    train_x, train_y, train_ids = load_split(args.data, "train", eval_views=False)
    test_data = args.test_data or args.data
    test_x, test_y, test_ids = load_split(test_data, "test", eval_views=True)
    # The training assets seen through the evaluation's views: far above the test accuracy
    # means the probe memorises its training set (limited by data, not by steps).
    fit_x, fit_y, _ = load_split(args.data, "train", eval_views=True)
    net = probe_net(len(MATERIAL_NAMES))
    opt = torch.optim.AdamW(net.parameters(), lr=args.lr, weight_decay=0.05)
    gen = torch.Generator().manual_seed(args.seed)
    start, steps, curve = time.perf_counter(), 0, []
    while time.perf_counter() - start < args.seconds and steps < max_steps:
        a = torch.randint(0, len(train_y), (args.batch,), generator=gen)
        v = torch.randint(0, train_x.shape[1], (args.batch,), generator=gen)
        x = train_x[a, v]
        if torch.rand((), generator=gen) < 0.5:
            x = x.flip(-1)
        loss = F.cross_entropy(net(x), train_y[a])
        opt.zero_grad()
        loss.backward()
        opt.step()
        steps += 1
        if steps % 300 == 0:
            curve.append(
                {
                    "step": steps,
                    "seconds": round(time.perf_counter() - start, 1),
                    "train_loss": round(loss.item(), 4),
                    "test_accuracy_1_view": accuracy(net, test_x, test_y)[0],
                }
            )
    one, four = accuracy(net, test_x, test_y)
    train_one, train_four = accuracy(net, fit_x, fit_y)
    report = {
        "data": args.data,
        "test_data": test_data,
        "train_assets": len(train_ids),
        "test_assets": len(test_ids),
        "resolution": list(train_x.shape[-2:]),
        "steps": steps,
        "seconds": round(time.perf_counter() - start, 1),
        "test_accuracy_1_view": one,
        "test_accuracy_4_views": four,
        "train_accuracy_1_view": train_one,
        "train_accuracy_4_views": train_four,
        "majority_class_accuracy": float(torch.bincount(test_y).max()) / len(test_y),
        "curve": curve,
    }
    print(json.dumps(report))
    return report


if __name__ == "__main__":
    main()
