import numpy as np
import pytest
import torch

from physgm.gaussians import Gaussians, quat_to_rotmat, read_ply, rotmat_to_quat, write_ply


def random_gaussians(n: int, seed: int = 0, sh_k: int = 0) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1)
    return Gaussians(
        means=torch.randn(n, 3, generator=g),
        quats=quats * torch.where(quats[:, :1] < 0, -1.0, 1.0),
        scales=torch.rand(n, 3, generator=g) * 0.1 + 1e-3,
        opacities=torch.rand(n, generator=g) * 0.98 + 0.01,
        colors=torch.rand(n, 3, generator=g),
        sh_rest=torch.randn(n, sh_k, 3, generator=g) if sh_k else None,
    )


@pytest.mark.parametrize("sh_k", [0, 15])
def test_ply_round_trip_exact(tmp_path, sh_k):
    g = random_gaussians(257, sh_k=sh_k)
    write_ply(g, tmp_path / "g.ply")
    back = read_ply(tmp_path / "g.ply")
    for name in ["means", "quats", "scales", "opacities", "colors"]:
        torch.testing.assert_close(getattr(back, name), getattr(g, name), atol=1e-6, rtol=1e-6, msg=name)
    if sh_k:
        torch.testing.assert_close(back.sh_rest, g.sh_rest, atol=1e-6, rtol=0)
    assert not list(tmp_path.glob(".*tmp*")), "temporary file left behind"


def test_ply_layout_is_standard_3dgs(tmp_path):
    from plyfile import PlyData

    write_ply(random_gaussians(4, sh_k=3), tmp_path / "g.ply")
    names = [p.name for p in PlyData.read(str(tmp_path / "g.ply"))["vertex"].properties]
    expected = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [
        f"f_rest_{i}" for i in range(9)
    ]
    expected += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert names == expected


def test_ply_stored_values_use_3dgs_activations(tmp_path):
    from plyfile import PlyData

    g = random_gaussians(8)
    write_ply(g, tmp_path / "g.ply")
    v = PlyData.read(str(tmp_path / "g.ply"))["vertex"]
    np.testing.assert_allclose(1 / (1 + np.exp(-np.asarray(v["opacity"]))), g.opacities.numpy(), atol=1e-6)
    np.testing.assert_allclose(np.exp(np.asarray(v["scale_1"])), g.scales[:, 1].numpy(), rtol=1e-6)
    np.testing.assert_allclose(
        np.asarray(v["f_dc_0"]) * 0.28209479177387814 + 0.5, g.colors[:, 0].numpy(), atol=1e-6
    )


def test_read_ply_drops_sh_with_warning(tmp_path):
    write_ply(random_gaussians(5, sh_k=8), tmp_path / "g.ply")
    with pytest.warns(UserWarning, match="dropping SH degree 2"):
        back = read_ply(tmp_path / "g.ply", keep_sh=False)
    assert back.sh_rest is None and len(back) == 5


def test_read_ply_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="no PLY file"):
        read_ply(tmp_path / "missing.ply")
    (tmp_path / "junk.ply").write_bytes(b"not a ply at all")
    with pytest.raises(ValueError, match="not a readable PLY"):
        read_ply(tmp_path / "junk.ply")
    import trimesh

    trimesh.creation.box().export(tmp_path / "mesh.ply")
    with pytest.raises(ValueError, match="not a 3D Gaussian Splatting PLY"):
        read_ply(tmp_path / "mesh.ply")


def test_empty_round_trip(tmp_path):
    g = random_gaussians(0)
    write_ply(g, tmp_path / "e.ply")
    assert len(read_ply(tmp_path / "e.ply")) == 0


def test_indexing_cat_prune_and_shapes():
    g = random_gaussians(10)
    assert len(g[g.opacities > 0.5]) == int((g.opacities > 0.5).sum())
    assert len(g[2:5]) == 3
    both = Gaussians.cat([g, g[:3]])
    assert len(both) == 13
    torch.testing.assert_close(both.means[10:], g.means[:3])
    assert len(g.prune(0.5)) == int((g.opacities >= 0.5).sum())
    with pytest.raises(ValueError, match=r"Gaussians.quats must have shape \[N, 4\]"):
        Gaussians(g.means, g.quats[:, :3], g.scales, g.opacities, g.colors)
    with pytest.raises(ValueError, match="at least one"):
        Gaussians.cat([])


def test_covariance_matches_definition():
    g = random_gaussians(6)
    cov = g.covariances()
    R = quat_to_rotmat(g.quats)
    ref = R @ torch.diag_embed(g.scales**2) @ R.transpose(1, 2)
    torch.testing.assert_close(cov, ref)
    assert torch.allclose(cov, cov.transpose(1, 2))


def test_rotation_quaternion_round_trip():
    q = torch.nn.functional.normalize(random_gaussians(1000, seed=3).quats.double(), dim=-1)
    R = quat_to_rotmat(q)
    torch.testing.assert_close(
        R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(1000, 3, 3), atol=1e-12, rtol=0
    )
    torch.testing.assert_close(rotmat_to_quat(R), q, atol=1e-10, rtol=0)
