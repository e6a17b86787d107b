"""Stage-1 test metrics of a checkpoint on a held-out split, for 1 and for 4 input views.

    python -m physgm.train.evaluate CKPT --data ROOT [--split test] [--views 1,4] [--out metrics.json]

For every asset of the split the model sees the fixed evaluation inputs (view 1 is the
canonical camera; with 4 views the other three follow around the object, as in training)
and renders the target views it did not see. Reported per input-view count: PSNR, SSIM
(and LPIPS when its backbone file is given) on those novel views; ``psnr_inputs``, the PSNR of
the input views rendered back (low when the Gaussians' depths are wrong, since the other
views' Gaussians then cover them), and the median opacity of the predicted Gaussians;
material accuracy and confusion matrix, |log10 E - true|, |nu - true|, NLL and 90 % interval
coverage against the *true* physics of each asset. One JSON object goes to stdout.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

from physgm.data.datamodule import PhysAssetsDataModule
from physgm.metrics.image import ImageMetrics
from physgm.metrics.physics_metrics import PhysicsMetrics
from physgm.physics.materials import MATERIAL_NAMES
from physgm.train.pretrain import model_from_checkpoint, render_targets


def checkpoint_renderer(path: str) -> dict:
    """The renderer settings the checkpoint trained with (warp by default)."""
    hp = torch.load(path, map_location="cpu", weights_only=False).get("hyper_parameters", {})
    return dict(hp.get("renderer") or {"backend": "warp"})


@torch.no_grad()
def evaluate_views(
    model,
    datamodule: PhysAssetsDataModule,
    renderer: dict,
    lpips_model: torch.nn.Module | None = None,
) -> dict:
    """Metrics of ``model`` over the datamodule's test split, whose eval_p_single fixes the view count."""
    images = ImageMetrics()
    seen = ImageMetrics()  # the input views rendered back: tells geometry errors from colour errors
    physics = PhysicsMetrics(len(MATERIAL_NAMES))
    lpips_sum, lpips_count, assets, gaussians = 0.0, 0, 0, 0.0
    opacities = []
    for batch in datamodule.test_dataloader():
        views = batch.images.shape[1]
        out = model(batch.images, batch.masks, batch.c2w, batch.Ks)
        h, w = batch.target_images.shape[-2:]
        rgb, _ = render_targets(out, batch.target_c2w, batch.target_Ks, w, h, renderer)
        rendered = rgb.permute(0, 1, 4, 2, 3).clamp(0, 1)
        pred = rendered[:, views:].flatten(0, 1)  # novel views only
        target = batch.target_images[:, views:].flatten(0, 1)
        images.update(pred, target)
        seen.update(rendered[:, :views].flatten(0, 1), batch.target_images[:, :views].flatten(0, 1))
        opacities.append(out.gaussians.opacities[out.gaussians.valid])
        if lpips_model is not None:  # lpips takes images in [-1, 1]
            lpips_sum += float(lpips_model(pred * 2 - 1, target * 2 - 1).sum())
            lpips_count += pred.shape[0]
        known = batch.true_known
        if known.any():
            physics.update(
                out.physics[known],
                batch.true_material[known],
                batch.true_log10_E[known],
                batch.true_nu[known],
            )
        assets += batch.images.shape[0]
        gaussians += float(out.gaussians.count.float().sum())
    if not assets:
        raise ValueError(
            f"split {datamodule.hparams.test_split!r} of {datamodule.hparams.root} has no assets"
        )
    result = {"assets": assets, "gaussians_mean": gaussians / assets}
    result.update({k: float(v) for k, v in images.compute().items()})
    result["psnr_inputs"] = float(seen.compute()["psnr"])
    result["opacity_median"] = float(torch.cat(opacities).median())
    if lpips_count:
        result["lpips"] = lpips_sum / lpips_count
    if physics.update_count:
        scores = physics.compute()
        confusion = scores.pop("confusion")
        result.update({k: float(v) for k, v in scores.items()})
        result["confusion"] = {"rows_true_cols_pred": list(MATERIAL_NAMES), "matrix": confusion.tolist()}
    return result


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m physgm.train.evaluate", description=__doc__.split("\n")[0])
    p.add_argument("ckpt", help="stage-1 or stage-2 checkpoint")
    p.add_argument("--data", required=True, help="PhysAssets root with splits/")
    p.add_argument("--split", default="test")
    p.add_argument("--views", default="1,4", help="comma-separated input-view counts (1 and/or 4)")
    p.add_argument("--num-targets", type=int, default=8, help="target views per asset, inputs included")
    p.add_argument(
        "--resolution", type=int, default=None, help="target size, px (default: the model's input size)"
    )
    p.add_argument("--batch-size", type=int, default=4)
    p.add_argument(
        "--lpips-backbone", default=None, help="local LPIPS backbone file; adds LPIPS (see README)"
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the fixed evaluation views")
    p.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    a = p.parse_args(argv)

    views = sorted({int(v) for v in a.views.split(",")})
    if not set(views) <= {1, 4}:
        raise SystemExit(f"--views takes 1 and/or 4, got {a.views!r}")
    if not Path(a.ckpt).is_file():
        raise SystemExit(f"checkpoint {a.ckpt} not found")
    model = model_from_checkpoint(a.ckpt).eval()
    renderer = checkpoint_renderer(a.ckpt)
    res = model.config.backbone.encoder.img_size
    lpips_model = None
    if a.lpips_backbone:
        from physgm.metrics.lpips import load_lpips

        lpips_model = load_lpips("alex", a.lpips_backbone)
    report = {"ckpt": a.ckpt, "data": a.data, "split": a.split, "input_resolution": res,
              "target_resolution": a.resolution or res, "num_targets": a.num_targets}
    start = time.perf_counter()
    for v in views:
        dm = PhysAssetsDataModule(
            a.data,
            batch_size=a.batch_size,
            eval_p_single=1.0 if v == 1 else 0.0,
            num_targets=a.num_targets,
            input_resolution=res,
            target_resolution=a.resolution or res,
            test_split=a.split,
            val_split=a.split,
            seed=a.seed,
        )
        report[f"views{v}"] = evaluate_views(model, dm, renderer, lpips_model)
        print(f"{v} view(s): " + ", ".join(f"{k}={x:.4g}" for k, x in report[f"views{v}"].items()
                                           if isinstance(x, float)), file=sys.stderr, flush=True)
    report["seconds"] = round(time.perf_counter() - start, 1)
    text = json.dumps(report)
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        tmp = a.out.with_suffix(a.out.suffix + ".tmp")
        tmp.write_text(text)
        tmp.replace(a.out)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
