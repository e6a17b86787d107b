"""Stage-1 training: configs compose and run, the model overfits a batch, resume and checkpoints work."""

from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra

from physgm.data.datamodule import PhysAssetsDataModule
from physgm.errors import UserError
from physgm.model.checkpoint import load_model
from physgm.train.pretrain import LitPretrain
from physgm.train.run import main, run

CONF = Path(__file__).resolve().parents[2] / "conf"
EXPERIMENTS = sorted(
    p.stem for p in (CONF / "experiment").glob("*.yaml") if not p.stem.endswith("_dpo")
)  # DPO: test_rollout


def tiny_overrides(root: Path, out: Path) -> list[str]:
    return [
        "trainer=cpu",
        "renderer=warp",
        "synth=null",
        "logger=csv",
        f"data.root={root}",
        "data.val_split=train",
        "data.test_split=train",
        "data.num_workers=0",
        "data.batch_size=2",
        "data.input_resolution=32",
        "data.target_resolution=32",
        "data.num_targets=5",
        f"paths.output_dir={out}",
    ]


def compose_train(overrides: list[str]):
    GlobalHydra.instance().clear()
    with initialize_config_dir(str(CONF), version_base="1.3"):
        return compose("train", overrides=overrides)


def shrink_paper(tmp_path: Path) -> list[str]:
    """The paper's code path (DINOv3 encoder from a local file, DPT, DDP config) at a CPU-test size."""
    import timm
    import torchvision

    weights = tmp_path / "dinov3_vits16.pth"
    torch.save(
        timm.create_model("vit_small_patch16_dinov3", pretrained=False, num_classes=0).state_dict(), weights
    )
    alexnet = (
        tmp_path / "alexnet.pth"
    )  # LPIPS is on in the paper config; a random local backbone exercises it
    torch.save(torchvision.models.alexnet().state_dict(), alexnet)
    return [
        f"stage.loss.lpips_backbone_path={alexnet}",
        "model.backbone.encoder.arch=vit_small_patch16_dinov3",
        f"model.backbone.encoder.weights={weights}",
        "model.backbone.encoder.embed_dim=384",
        "model.backbone.encoder.depth=12",
        "model.backbone.encoder.num_heads=6",
        "model.backbone.encoder.img_size=32",
        "model.backbone.width=128",
        "model.backbone.depth=4",
        "model.backbone.out_layers=[0,1,2,3]",
        "data.batch_size=1",
        "data.p_single=0.0",
        "data.eval_p_single=0.0",
        "trainer.precision=32-true",
    ]


@pytest.mark.parametrize("experiment", EXPERIMENTS)
def test_fast_dev_run_every_experiment(experiment, tiny_dataset, tmp_path):
    overrides = [
        f"experiment={experiment}",
        *tiny_overrides(tiny_dataset, tmp_path / "run"),
        "+trainer.fast_dev_run=1",
    ]
    if experiment == "paper":
        overrides += shrink_paper(tmp_path)
    metrics = run(compose_train(overrides))
    assert torch.isfinite(torch.tensor(metrics["train/loss"]))


def two_steps_with(root: Path, out: Path, *term: str) -> list[str]:
    """A two-step tiny_cpu run with one validation batch, plus the overrides that turn a loss term on."""
    return [
        "experiment=tiny_cpu",
        *tiny_overrides(root, out),
        *term,
        "trainer.max_steps=2",
        "trainer.val_check_interval=2",
        "trainer.limit_val_batches=1",
    ]


def test_the_surface_term_trains_and_validates_end_to_end(tiny_dataset, tmp_path):
    overrides = two_steps_with(
        tiny_dataset, tmp_path / "run", "data.surface_points=32", "stage.loss.surface=1.0"
    )
    metrics = run(compose_train(overrides))
    assert metrics["train/surface"] > 0 and torch.isfinite(torch.tensor(metrics["train/loss"]))
    # the weight without the points is a clear error, not a silent zero
    with pytest.raises(ValueError, match="data.surface_points"):
        run(compose_train([*overrides, "data.surface_points=0", "trainer.max_steps=1"]))


def test_the_perceptual_term_on_the_frozen_mobilenet_trains_without_a_backbone_file(tiny_dataset, tmp_path):
    """The paper's LPIPS term on the CPU: ``lpips_net=mobilenet`` needs no torchvision file."""
    overrides = two_steps_with(
        tiny_dataset, tmp_path / "run", "stage.loss.lpips=0.5", "stage.loss.lpips_net=mobilenet"
    )
    metrics = run(compose_train(overrides))
    assert metrics["train/lpips"] > 0 and torch.isfinite(torch.tensor(metrics["train/loss"]))


def test_resume_continues_step_count_and_checkpoint_predicts_the_same(tiny_dataset, tmp_path):
    out = tmp_path / "run"
    base = [
        *tiny_overrides(tiny_dataset, out),
        "callbacks.model_checkpoint.every_n_train_steps=2",
        "trainer.val_check_interval=2",
        "trainer.limit_val_batches=1",
    ]
    run(compose_train([*base, "trainer.max_steps=2"]))
    last = out / "checkpoints" / "last.ckpt"
    assert torch.load(last, weights_only=False)["global_step"] == 2
    run(compose_train([*base, "trainer.max_steps=4", "ckpt_path=last"]))
    ckpt = torch.load(last, weights_only=False)
    assert ckpt["global_step"] == 4
    assert not any("lpips" in k for k in ckpt["state_dict"]), "a frozen LPIPS net must not be saved"

    # The checkpoint rebuilds outside Hydra and Lightning and predicts what the trained module predicts.
    module = LitPretrain.load_from_checkpoint(last, map_location="cpu").eval()
    model, _ = load_model(last)
    dm = PhysAssetsDataModule(
        root=str(tiny_dataset),
        val_split="train",
        input_resolution=32,
        target_resolution=32,
        num_targets=5,
        batch_size=2,
        eval_p_single=0.0,
    )
    dm.setup("validate")
    batch = next(iter(dm.val_dataloader()))
    with torch.no_grad():
        a, b = module(batch), model(batch.images, batch.masks, batch.c2w, batch.Ks)
    torch.testing.assert_close(a.gaussians.means, b.gaussians.means, rtol=0, atol=0)
    torch.testing.assert_close(a.physics.material_logits, b.physics.material_logits, rtol=0, atol=0)


def test_last_checkpoint_is_written_when_training_stops_between_saves(tiny_dataset, tmp_path):
    """max_steps (or max_time) between two intervals: last.ckpt still holds the final step."""
    out = tmp_path / "run"
    run(
        compose_train(
            [
                *tiny_overrides(tiny_dataset, out),
                "callbacks.model_checkpoint.every_n_train_steps=2",
                "callbacks.snapshots.every_n_train_steps=2",
                "trainer.max_steps=3",
                "trainer.limit_val_batches=0",
            ]
        )
    )
    ckpts = out / "checkpoints"
    assert torch.load(ckpts / "last.ckpt", weights_only=False)["global_step"] == 3
    assert sorted(p.name for p in ckpts.glob("step*.ckpt")) == ["step0000002.ckpt"]


def test_overfits_one_batch(tiny_dataset):
    """Rendered MSE + alpha + material CE on one batch fall at least 10x."""
    torch.manual_seed(0)
    dm = PhysAssetsDataModule(
        root=str(tiny_dataset),
        input_resolution=32,
        target_resolution=32,
        num_targets=4,
        batch_size=2,
        p_single=0.0,
        val_split="train",
    )
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    module = LitPretrain(optim={"lr": 2e-3, "warmup_steps": 0}, loss={"nll": 0.0}, total_steps=10**6)
    opt = torch.optim.AdamW(module.parameters(), lr=2e-3, betas=(0.9, 0.95))

    def objective() -> torch.Tensor:
        _, _, _, terms = module._losses(batch)
        return terms["mse"] + terms["alpha"] + terms["ce"]

    first = objective().item()
    for _ in range(150):
        opt.zero_grad()
        loss = objective()
        loss.backward()
        opt.step()
    assert objective().item() < first / 10, (first, loss.item())


def test_train_py_shows_a_settings_mistake_as_one_error_line(tiny_dataset, tmp_path, capsys):
    for override, message in [
        ("stage.trainable=backbone", "error: stage.trainable must be one of"),
        ("stage.name=finetune", "error: unknown stage 'finetune'"),
        ("torch_threads=-1", "error: torch_threads must be >= 0"),
        # checked before the data set, which a run without one spends minutes generating
        ("stage.optim.lr=fast", "error: bad stage settings: optim setting lr='fast' must be a number"),
        ("stage.loss.ce=yes", "error: bad stage settings: loss setting ce='yes' must be a number"),
    ]:
        with pytest.raises(SystemExit) as stop:
            main(compose_train([*tiny_overrides(tiny_dataset, tmp_path / "bad"), override]))
        err = capsys.readouterr().err
        assert stop.value.code == 2 and err.startswith(message) and "Traceback" not in err, err


def test_gaussian_head_fine_tune_keeps_every_other_weight_and_the_init_models_config(tiny_dataset, tmp_path):
    """stage.trainable=gaussian_head: the init checkpoint's model config whole (here its E offset, which
    the run's own config does not have), only the Gaussian head moves, and the frozen parts stay in
    eval mode."""
    first = tmp_path / "first"
    base = [*tiny_overrides(tiny_dataset, first), "trainer.max_steps=2", "trainer.limit_val_batches=0"]
    run(compose_train([*base, "model.physics_head.E_logvar_offset=0.7"]))
    init = first / "checkpoints" / "last.ckpt"
    out = tmp_path / "head"
    tuned = [
        *tiny_overrides(tiny_dataset, out),
        "trainer.max_steps=3",
        "trainer.limit_val_batches=0",
        "stage.trainable=gaussian_head",
        f"stage.init_ckpt={init}",
        "stage.optim.lr=1e-2",
    ]
    run(compose_train(tuned))
    before = torch.load(init, weights_only=False)
    after = torch.load(out / "checkpoints" / "last.ckpt", weights_only=False)
    assert after["hyper_parameters"]["model"] == before["hyper_parameters"]["model"]
    assert after["hyper_parameters"]["model"]["physics_head"]["E_logvar_offset"] == 0.7
    moved = {k for k, v in before["state_dict"].items() if not torch.equal(v, after["state_dict"][k])}
    assert moved and all(k.startswith("model.gaussian_head.") for k in moved), sorted(moved)[:5]
    module = LitPretrain(model=before["hyper_parameters"]["model"], trainable="gaussian_head").train()
    assert module.model.gaussian_head.training and not module.model.backbone.training
    assert not module.model.physics_head.training
    assert all(not m.training for n, m in module.model.named_children() if n != "gaussian_head")
    with pytest.raises(UserError, match="stage.init_ckpt"):
        run(compose_train([*tiny_overrides(tiny_dataset, tmp_path / "no"), "stage.trainable=gaussian_head"]))
    with pytest.raises(ValueError, match="stage.trainable"):
        LitPretrain(trainable="backbone")
    with pytest.raises(UserError, match="stage.trainable"):
        run(compose_train([*tiny_overrides(tiny_dataset, tmp_path / "bad"), "stage.trainable=backbone"]))


def _tokens(ckpt: Path) -> torch.Tensor:  # [1, G, D] for two fixed random views
    model, _ = load_model(ckpt)
    g = torch.Generator().manual_seed(0)
    images = torch.rand(1, 2, 3, 32, 32, generator=g)
    c2w = torch.eye(4).expand(1, 2, 4, 4).clone()
    c2w[0, 1, :3, 3] = torch.tensor([0.3, 0.0, 0.0])
    Ks = torch.tensor([[32.0, 0.0, 16.0], [0.0, 32.0, 16.0], [0.0, 0.0, 1.0]]).expand(1, 2, 3, 3)
    with torch.no_grad():
        return model.global_tokens(images, c2w, Ks)


def test_geometry_fine_tune_trains_the_backbone_and_the_anchor_holds_the_physics_tokens(
    tiny_dataset, tmp_path
):
    """stage.trainable=geometry: the backbone and the Gaussian head move, the physics head does not;
    loss.anchor keeps the global tokens (all the physics head reads) near the starting model's."""
    first = tmp_path / "first"
    run(
        compose_train(
            [*tiny_overrides(tiny_dataset, first), "trainer.max_steps=2", "trainer.limit_val_batches=0"]
        )
    )
    init = first / "checkpoints" / "last.ckpt"
    start, drift, metrics = _tokens(init), {}, {}
    for anchor in (0.0, 100.0):
        out = tmp_path / f"anchor{anchor:g}"
        tuned = [
            *tiny_overrides(tiny_dataset, out),
            "trainer.max_steps=4",
            "trainer.limit_val_batches=0",
            "stage.trainable=geometry",
            f"stage.init_ckpt={init}",
            f"stage.loss.anchor={anchor}",
            "stage.optim.lr=1e-2",
            "stage.optim.warmup_steps=0",
        ]
        metrics[anchor] = run(compose_train(tuned))
        before = torch.load(init, weights_only=False)["state_dict"]
        after = torch.load(out / "checkpoints" / "last.ckpt", weights_only=False)["state_dict"]
        moved = {k for k, v in before.items() if not torch.equal(v, after[k])}
        assert any(k.startswith("model.backbone.") for k in moved), sorted(moved)[:5]
        assert all(k.startswith(("model.backbone.", "model.gaussian_head.")) for k in moved), sorted(moved)
        tokens = _tokens(out / "checkpoints" / "last.ckpt")
        drift[anchor] = float(((tokens - start).square().sum(-1) / start.square().sum(-1)).mean())
    assert "train/anchor" not in metrics[0.0] and metrics[100.0]["train/anchor"] >= 0
    assert drift[100.0] < drift[0.0] / 4, drift
    module = LitPretrain(
        model=torch.load(init, weights_only=False)["hyper_parameters"]["model"], trainable="geometry"
    )
    module.train()
    assert module.model.backbone.training and module.model.gaussian_head.training
    assert not module.model.physics_head.training
    with pytest.raises(UserError, match="stage.trainable=geometry"):
        run(compose_train([*tiny_overrides(tiny_dataset, tmp_path / "no"), "stage.loss.anchor=1"]))


def _fine_tune(tiny_dataset, out, init, *settings: str) -> list[str]:
    """Overrides of a 3-step fine-tune from ``init`` into ``out`` at a large learning rate."""
    return [
        *tiny_overrides(tiny_dataset, out),
        "trainer.max_steps=3",
        "trainer.limit_val_batches=0",
        *settings,
        f"stage.init_ckpt={init}",
        "stage.optim.lr=1e-2",
        "stage.optim.warmup_steps=0",
    ]


def test_geometry_blocks_fine_tune_moves_the_gaussians_and_leaves_the_physics_bit_identical(
    tiny_dataset, tmp_path
):
    """stage.trainable=geometry_blocks: the Gaussian head and its own copies of the backbone's last
    blocks train; every weight the checkpoint had but the Gaussian head's is unchanged, the global
    tokens (all the physics head reads) are bit-identical, and the frozen parts stay in eval mode.
    A later run may give the head copies of more blocks, never fewer."""
    first = tmp_path / "first"
    base = [*tiny_overrides(tiny_dataset, first), "trainer.max_steps=2", "trainer.limit_val_batches=0"]
    run(compose_train(base))
    init = first / "checkpoints" / "last.ckpt"
    out = tmp_path / "blocks"
    tuned = _fine_tune(tiny_dataset, out, init, "stage.trainable=geometry_blocks", "stage.geometry_blocks=2")
    run(compose_train(tuned))
    before = torch.load(init, weights_only=False)
    after = torch.load(out / "checkpoints" / "last.ckpt", weights_only=False)
    model = after["hyper_parameters"]["model"]
    assert model["backbone"]["geometry_blocks"] == 2
    shared = {**model, "backbone": {**model["backbone"], "geometry_blocks": 0}}
    assert shared == before["hyper_parameters"]["model"]  # the checkpoint's config but the new blocks
    moved = {k for k, v in before["state_dict"].items() if not torch.equal(v, after["state_dict"][k])}
    assert moved and all(k.startswith("model.gaussian_head.") for k in moved), sorted(moved)[:5]
    own = [k for k in after["state_dict"] if k.startswith("model.backbone.geometry_blocks.")]
    depth = model["backbone"]["depth"]
    copies = {k: k.replace("geometry_blocks.0.", f"blocks.{depth - 2}.") for k in own if ".0." in k}
    assert any(not torch.equal(after["state_dict"][k], before["state_dict"][v]) for k, v in copies.items())
    assert torch.equal(_tokens(out / "checkpoints" / "last.ckpt"), _tokens(init))

    module = LitPretrain(model=model, trainable="geometry_blocks").train()
    assert module.model.gaussian_head.training and module.model.backbone.geometry_blocks.training
    assert not any(m.training for m in (module.model.backbone.blocks, module.model.backbone.fuse))
    assert not module.model.physics_head.training

    settings = [o for o in tuned if not o.startswith(("stage.geometry_blocks", "stage.init_ckpt"))]
    with pytest.raises(UserError, match="give 1 to"):
        run(compose_train([*settings, f"stage.init_ckpt={init}", "stage.geometry_blocks=0"]))
    again = f"stage.init_ckpt={out / 'checkpoints' / 'last.ckpt'}"
    with pytest.raises(UserError, match="stage.geometry_blocks=2 to train them further"):
        run(compose_train([*settings, again, "stage.geometry_blocks=1"]))
    # More copies than the checkpoint's: the physics is still the first run's to the bit.
    grown, tuned_file = tmp_path / "grown", out / "checkpoints" / "last.ckpt"
    blocks3 = ("stage.trainable=geometry_blocks", "stage.geometry_blocks=3")
    run(compose_train(_fine_tune(tiny_dataset, grown, tuned_file, *blocks3)))
    grown_file = torch.load(grown / "checkpoints" / "last.ckpt", weights_only=False)
    assert grown_file["hyper_parameters"]["model"]["backbone"]["geometry_blocks"] == 3
    assert torch.equal(_tokens(grown / "checkpoints" / "last.ckpt"), _tokens(init))


def test_a_gaussian_layer_added_to_a_trained_model_trains_and_leaves_the_physics_bit_identical(
    tiny_dataset, tmp_path
):
    """stage.gaussian_layers=2 on a one-layer checkpoint: the run's model has two Gaussians per
    pixel, the new layer's conv starts as the first's and trains, the global tokens are the
    checkpoint's to the bit, and fewer layers than the checkpoint's is refused."""
    first = tmp_path / "first"
    run(
        compose_train(
            [*tiny_overrides(tiny_dataset, first), "trainer.max_steps=1", "trainer.limit_val_batches=0"]
        )
    )
    init = first / "checkpoints" / "last.ckpt"
    out = tmp_path / "layers"
    tuned = _fine_tune(tiny_dataset, out, init, "stage.trainable=gaussian_head", "stage.gaussian_layers=2")
    run(compose_train(tuned))
    before = torch.load(init, weights_only=False)
    after = torch.load(out / "checkpoints" / "last.ckpt", weights_only=False)
    assert after["hyper_parameters"]["model"]["gaussian_head"]["layers"] == 2
    last = max(
        int(k.split(".")[4]) for k in before["state_dict"] if k.startswith("model.gaussian_head.dpt.output.")
    )
    start = before["state_dict"][f"model.gaussian_head.dpt.output.{last}.weight"]
    grown = after["state_dict"]["model.gaussian_head.dpt.layer_outputs.0.weight"]
    assert grown.shape == start.shape and not torch.equal(grown, start)
    assert torch.equal(_tokens(out / "checkpoints" / "last.ckpt"), _tokens(init))

    again = f"stage.init_ckpt={out / 'checkpoints' / 'last.ckpt'}"
    settings = [o for o in tuned if not o.startswith(("stage.gaussian_layers", "stage.init_ckpt"))]
    with pytest.raises(UserError, match="already has 2 Gaussian layers"):
        run(compose_train([*settings, again, "stage.gaussian_layers=1"]))
