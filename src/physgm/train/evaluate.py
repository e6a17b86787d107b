"""Stage-1 test metrics of a checkpoint on a held-out split, for 1 and for 4 input views.

    python -m physgm.train.evaluate CKPT --data ROOT [--split test] [--views 1,4] [--out metrics.json]

For every asset of the split the model sees the fixed evaluation inputs (view 1 is the
canonical camera; with 4 views the other three follow around the object, as in training)
and renders the target views it did not see. Reported per input-view count: PSNR, SSIM
(and LPIPS when its backbone file is given) on those novel views; where their squared error lies
(``error_outside_mask``: its share outside the object's mask, the haze around the object;
``alpha_outside_mask``, the rendered opacity there) and how it grows with the angle from the
nearest input camera (``psnr_by_angle``, 30 degree bins); ``psnr_inputs``, the PSNR of
the input views rendered back (low when the Gaussians' depths are wrong, since the other
views' Gaussians then cover them), and the median opacity of the predicted Gaussians;
material and behaviour-class accuracy and the confusion matrix, |log10 E - true|, |nu - true|,
NLL and 90 % interval coverage against the *true* physics of each asset. Assets without true
physics (real objects: imported meshes with a hand or annotator label) are scored on material
and behaviour accuracy against their label (``label_*``).

With the frozen MobileNetV2 encoder the material distribution is p_head * p_prior^w
(``physgm.model.semantic_prior``): ``--prior-weight`` sets w (default: the checkpoint's), and
``--prior-sweep 0,0.5,1,2`` also reports both accuracies at each w, which is how w is chosen on
the real validation objects; ``prior_only_*`` scores the semantic table alone (zero-shot). A model
with a domain gate (``physgm.model.domain_gate``) mixes that with p_head by the gate's P(real
object) g, at every w, and ``domain_gate`` gives that probability's 10th, 50th and 90th
percentiles. ``--max-assets N`` scores N assets spread evenly over the split list; on the training
split (``--split train --max-assets 250``) it tells how far the model is from fitting what it was
trained on. One JSON object goes to stdout.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import torch

from physgm.data.datamodule import PhysAssetsDataModule
from physgm.metrics.image import ErrorByAngle, ImageMetrics
from physgm.metrics.physics_metrics import LabelMetrics, PhysicsMetrics
from physgm.model.checkpoint import load_model
from physgm.model.physics_head import fuse_material_logits
from physgm.physics.materials import MATERIAL_NAMES
from physgm.train.pretrain import render_targets


def checkpoint_renderer(hparams: dict) -> dict:
    """The renderer settings a checkpoint (its ``hyper_parameters``) trained with (warp by default)."""
    return dict(hparams.get("renderer") or {"backend": "warp"})


def fused_logits(out, weight: float, temperature: float = 1.0) -> torch.Tensor:  # [B, M]
    """Material logits of a model output at any prior weight w, with its domain gate if it has one
    (``fuse_material_logits``)."""
    return fuse_material_logits(
        out.head_material_logits,
        out.semantic_log_prior,
        weight,
        temperature,
        out.domain_real,
        out.procedural_material_logits,
    )


def view_datamodule(
    model,
    root: str,
    split: str,
    views: int,
    resolution: int,
    num_targets: int = 8,
    target_resolution: int | None = None,
    seed: int = 0,
    batch_size: int = 4,
    max_assets: int | None = None,
) -> PhysAssetsDataModule:
    """The split's fixed evaluation inputs at one input-view count (1 or 4), read from the feature
    cache when ``model`` has the frozen CNN encoder; its ``test_dataloader`` iterates them
    (``max_assets``: at most that many assets, evenly spaced over the split list)."""
    return PhysAssetsDataModule(
        root,
        batch_size=batch_size,
        eval_p_single=1.0 if views == 1 else 0.0,
        num_targets=num_targets,
        input_resolution=resolution,
        target_resolution=target_resolution or resolution,
        test_split=split,
        val_split=split,
        seed=seed,
        feature_cache="mobilenet_v2" if model.config.backbone.encoder.kind == "mobilenet_v2" else None,
        max_eval_assets=max_assets,
    )


@torch.no_grad()
def evaluate_views(
    model,
    datamodule: PhysAssetsDataModule,
    renderer: dict,
    lpips_model: torch.nn.Module | None = None,
    prior_weight: float | None = None,
    prior_sweep: tuple[float, ...] = (),
    device: str = "cpu",
) -> dict:
    """Metrics of ``model`` over the datamodule's test split, whose eval_p_single fixes the view count.

    ``prior_weight``: w of the semantic prior (None: the model's); ``prior_sweep``: also score the
    material at each of these w.
    """
    weight = model.config.physics_head.semantic_prior_weight if prior_weight is None else prior_weight
    temperature = model.config.physics_head.material_temperature
    images = ImageMetrics().to(device)
    seen = ImageMetrics().to(
        device
    )  # the input views rendered back: tells geometry errors from colour errors
    by_angle = ErrorByAngle()
    physics = PhysicsMetrics(len(MATERIAL_NAMES)).to(device)
    labels = LabelMetrics(len(MATERIAL_NAMES)).to(device)
    zero_shot = LabelMetrics(len(MATERIAL_NAMES)).to(
        device
    )  # the semantic table alone, against label or truth
    sweep = {
        w: (PhysicsMetrics(len(MATERIAL_NAMES)).to(device), LabelMetrics(len(MATERIAL_NAMES)).to(device))
        for w in prior_sweep
    }
    lpips_sum, lpips_count, assets, gaussians, labelled = 0.0, 0, 0, 0.0, 0
    opacities = []
    squared_error = {"inside": 0.0, "outside": 0.0}  # summed over the novel views' pixels
    alpha_outside, outside_pixels = 0.0, 0.0
    confidence = {"head": [], "prior": []}  # [B] each: the most probable material's probability
    domain_real = []  # [B] the domain gate's P(real object), for a model with a gate
    for batch in datamodule.test_dataloader():
        batch = batch.to(device)
        views = batch.images.shape[1]
        out = model(batch.images, batch.masks, batch.c2w, batch.Ks, batch.features)
        posterior = dataclasses.replace(out.physics, material_logits=fused_logits(out, weight, temperature))
        h, w = batch.target_images.shape[-2:]
        rgb, alpha = render_targets(out, batch.target_c2w, batch.target_Ks, w, h, renderer)
        rendered = rgb.permute(0, 1, 4, 2, 3).clamp(0, 1)
        pred = rendered[:, views:].flatten(0, 1)  # novel views only
        target = batch.target_images[:, views:].flatten(0, 1)
        images.update(pred, target)
        inside = batch.target_masks[:, views:].flatten(0, 1) > 0.5  # [N, 1, H, W]
        error = ((pred - target) ** 2).mean(1, keepdim=True)  # [N, 1, H, W] over RGB
        by_angle.update(
            batch.c2w, batch.target_c2w[:, views:], error.mean((1, 2, 3)).view(rendered.shape[0], -1)
        )
        squared_error["inside"] += float(error[inside].sum())
        squared_error["outside"] += float(error[~inside].sum())
        alpha_outside += float(alpha[:, views:].flatten(0, 1).permute(0, 3, 1, 2)[~inside].sum())
        outside_pixels += float((~inside).sum())
        seen.update(rendered[:, :views].flatten(0, 1), batch.target_images[:, :views].flatten(0, 1))
        opacities.append(out.gaussians.opacities[out.gaussians.valid])
        if lpips_model is not None:  # lpips takes images in [-1, 1]
            lpips_sum += float(lpips_model(pred * 2 - 1, target * 2 - 1).sum())
            lpips_count += pred.shape[0]
        known = batch.true_known
        if known.any():
            physics.update(
                posterior[known], batch.true_material[known], batch.true_log10_E[known], batch.true_nu[known]
            )
        if (~known).any():
            labels.update(posterior.material_logits[~known], batch.material[~known])
            labelled += int((~known).sum())
        confidence["head"].append(out.head_material_logits.softmax(-1).amax(-1))
        if out.domain_real is not None:
            domain_real.append(out.domain_real)
        if out.semantic_log_prior is not None:
            confidence["prior"].append(out.semantic_log_prior.exp().amax(-1))
            zero_shot.update(out.semantic_log_prior, torch.where(known, batch.true_material, batch.material))
        for w, (p_metric, l_metric) in sweep.items():
            swept = dataclasses.replace(out.physics, material_logits=fused_logits(out, w, temperature))
            if known.any():
                p_metric.update(
                    swept[known], batch.true_material[known], batch.true_log10_E[known], batch.true_nu[known]
                )
            if (~known).any():
                l_metric.update(swept.material_logits[~known], batch.material[~known])
        assets += batch.images.shape[0]
        gaussians += float(out.gaussians.count.float().sum())
    if not assets:
        raise ValueError(
            f"split {datamodule.hparams.test_split!r} of {datamodule.hparams.root} has no assets"
        )
    result = {"assets": assets, "gaussians_mean": gaussians / assets, "prior_weight": weight}
    result.update({k: float(v) for k, v in images.compute().items()})
    result["psnr_by_angle"] = by_angle.compute()
    result["psnr_inputs"] = float(seen.compute()["psnr"])
    result["opacity_median"] = float(torch.cat(opacities).median())
    result["error_outside_mask"] = squared_error["outside"] / max(sum(squared_error.values()), 1e-12)
    result["alpha_outside_mask"] = alpha_outside / max(outside_pixels, 1.0)
    if lpips_count:
        result["lpips"] = lpips_sum / lpips_count
    levels = {"p10": 0.1, "p50": 0.5, "p90": 0.9}
    result["confidence"] = {
        source: {name: float(torch.cat(values).float().quantile(q)) for name, q in levels.items()}
        for source, values in confidence.items()
        if values
    }
    if domain_real:
        gate = torch.cat(domain_real).float()
        result["domain_gate"] = {name: float(gate.quantile(q)) for name, q in levels.items()}
    if physics.update_count:
        scores = physics.compute()
        confusion = scores.pop("confusion")
        result.update({k: float(v) for k, v in scores.items()})
        result["confusion"] = {"rows_true_cols_pred": list(MATERIAL_NAMES), "matrix": confusion.tolist()}
    if labels.update_count:
        scores = labels.compute()
        result["labelled_assets"] = labelled
        result["label_material_acc"] = float(scores["material_acc"])
        result["label_behaviour_acc"] = float(scores["behaviour_acc"])
        result["label_confusion"] = {
            "rows_label_cols_pred": list(MATERIAL_NAMES),
            "matrix": scores["confusion"].tolist(),
        }
    if zero_shot.update_count:
        scores = zero_shot.compute()
        result["prior_only_material_acc"] = float(scores["material_acc"])
        result["prior_only_behaviour_acc"] = float(scores["behaviour_acc"])
    if sweep:
        result["prior_sweep"] = {}
        for w, (p_metric, l_metric) in sweep.items():
            row = {}
            if p_metric.update_count:
                s = p_metric.compute()
                row.update(material_acc=float(s["material_acc"]), behaviour_acc=float(s["behaviour_acc"]))
            if l_metric.update_count:
                s = l_metric.compute()
                row.update(
                    label_material_acc=float(s["material_acc"]), label_behaviour_acc=float(s["behaviour_acc"])
                )
            result["prior_sweep"][str(w)] = row
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
        "--max-assets",
        type=int,
        default=None,
        help="score at most this many assets, evenly spaced over the split list (for example --split "
        "train --max-assets 250: how well the model fits what it was trained on)",
    )
    p.add_argument(
        "--lpips-backbone", default=None, help="local LPIPS backbone file; adds LPIPS (see README)"
    )
    p.add_argument(
        "--lpips-net",
        default=None,
        choices=["alex", "vgg", "mobilenet"],
        help="adds LPIPS with this network (default alex when --lpips-backbone is given); mobilenet "
        "needs no file: the baseline recipe on the frozen encoder (physgm.metrics.perceptual)",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the fixed evaluation views")
    p.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    p.add_argument(
        "--prior-weight", type=float, default=None, help="w of the semantic prior (default: the checkpoint's)"
    )
    p.add_argument("--prior-sweep", default="", help="comma-separated w values to also score the material at")
    p.add_argument(
        "--prior-temperature",
        type=float,
        default=None,
        help="temperature T of the semantic prior's classifier (default: the checkpoint's)",
    )
    p.add_argument("--device", default="cpu", help="cpu or cuda[:k]")
    a = p.parse_args(argv)

    views = sorted({int(v) for v in a.views.split(",")})
    if not set(views) <= {1, 4}:
        raise SystemExit(f"--views takes 1 and/or 4, got {a.views!r}")
    if a.max_assets is not None and a.max_assets < 1:
        raise SystemExit(f"--max-assets must be at least 1, got {a.max_assets}")
    if not Path(a.ckpt).is_file():
        raise SystemExit(f"checkpoint {a.ckpt} not found")
    if a.device.startswith("cuda") and not torch.cuda.is_available():
        raise SystemExit(f"--device {a.device}: CUDA is not available on this machine; use --device cpu")
    model, ckpt = load_model(a.ckpt, a.device)
    if a.prior_temperature is not None:
        if not a.prior_temperature > 0:
            raise SystemExit(f"--prior-temperature must be > 0, got {a.prior_temperature}")
        model.config.physics_head.semantic_prior_temperature = a.prior_temperature
    sweep = tuple(float(w) for w in a.prior_sweep.split(",") if w.strip())
    renderer = checkpoint_renderer(ckpt.hparams)
    res = model.config.backbone.encoder.img_size
    lpips_model, lpips_net = None, a.lpips_net or ("alex" if a.lpips_backbone else None)
    if lpips_net is not None:
        from physgm.metrics.lpips import load_lpips

        lpips_model = load_lpips(lpips_net, a.lpips_backbone)
    report = {
        "ckpt": a.ckpt,
        "data": a.data,
        "split": a.split,
        "max_assets": a.max_assets,
        "input_resolution": res,
        "target_resolution": a.resolution or res,
        "num_targets": a.num_targets,
        "prior_temperature": model.config.physics_head.semantic_prior_temperature,
        "lpips_net": lpips_net,
    }
    start = time.perf_counter()
    for v in views:
        dm = view_datamodule(
            model, a.data, a.split, v, res, a.num_targets, a.resolution, a.seed, a.batch_size, a.max_assets
        )
        report[f"views{v}"] = evaluate_views(
            model, dm, renderer, lpips_model, a.prior_weight, sweep, a.device
        )
        print(
            f"{v} view(s): "
            + ", ".join(f"{k}={x:.4g}" for k, x in report[f"views{v}"].items() if isinstance(x, float)),
            file=sys.stderr,
            flush=True,
        )
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
