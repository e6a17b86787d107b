import numpy as np
import pytest
import torch
import torchvision

from physgm.metrics.lpips import load_lpips, lpips_distance
from physgm.metrics.perceptual import perceptual_distance


def test_missing_backbone_says_what_to_do(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"alexnet-owt-7be5be79.pth.*stage.loss.lpips=0"):
        load_lpips("alex", tmp_path / "nothing.pth")


def test_local_backbone_is_loaded_not_random(tmp_path):
    torch.manual_seed(0)
    backbone = torchvision.models.alexnet()
    torch.save(backbone.state_dict(), tmp_path / "alex.pth")
    model = load_lpips("alex", tmp_path / "alex.pth")
    torch.testing.assert_close(model.net.slice1[0].weight, backbone.features[0].weight)
    torch.testing.assert_close(model.net.slice5[0].weight, backbone.features[10].weight)
    assert not any(p.requires_grad for p in model.parameters())
    img = torch.rand(2, 3, 32, 32)
    assert lpips_distance(model, img, img).item() == pytest.approx(0.0, abs=1e-6)
    assert lpips_distance(model, img, torch.rand(2, 3, 32, 32)).item() > 0.01


def test_wrong_file_is_rejected(tmp_path):
    torch.save({"something": torch.zeros(1)}, tmp_path / "bad.pth")
    with pytest.raises(ValueError, match="does not look like torchvision alex"):
        load_lpips("alex", tmp_path / "bad.pth")


def test_mobilenet_perceptual_needs_no_file_and_has_a_gradient_for_the_prediction_only():
    """``net="mobilenet"``: LPIPS's baseline recipe on the CPU model's frozen encoder, the same
    numbers as the clip distance of ``physgm.metrics.perceptual``, and a loss the renders can
    train against."""
    model = load_lpips("mobilenet")
    assert not any(p.requires_grad for p in model.parameters())
    torch.manual_seed(0)
    target = torch.rand(3, 3, 64, 64)
    pred = (target + 0.2 * torch.randn_like(target)).clamp(0, 1).requires_grad_(True)
    assert lpips_distance(model, target, target).item() == pytest.approx(0.0, abs=1e-7)
    d = lpips_distance(model, pred, target)
    d.backward()
    assert d.item() > 0.01 and pred.grad.abs().sum() > 0
    farther = lpips_distance(model, torch.rand(3, 3, 64, 64), target).item()
    assert farther > d.item()  # noise is farther than a perturbed copy
    # the clip distance reads the same numbers from uint8 frames
    as_frames = [
        (x.detach().permute(0, 2, 3, 1).numpy() * 255).round().astype(np.uint8) for x in (pred, target)
    ]
    quantised = [torch.from_numpy(f).permute(0, 3, 1, 2).float() / 255 for f in as_frames]
    assert perceptual_distance(as_frames[1], as_frames[0]) == pytest.approx(
        lpips_distance(model, quantised[0], quantised[1]).item(), rel=1e-5
    )
    with pytest.raises(ValueError, match="multiple of 16"):
        model(torch.rand(1, 3, 40, 40), torch.rand(1, 3, 40, 40))


def test_an_unknown_net_names_the_known_ones():
    with pytest.raises(ValueError, match="mobilenet"):
        load_lpips("resnet")
