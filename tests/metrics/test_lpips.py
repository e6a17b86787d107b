import pytest
import torch
import torchvision

from physgm.metrics.lpips import load_lpips, lpips_distance


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
