"""gaussians_t.npz: what simulate.py writes for the viewer, and how the viewer finds and reads it."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from physgm.view.sequence import (
    FORMAT_VERSION,
    SEQUENCE_FILE,
    GaussianSequence,
    matrix_to_triu,
    sequence_file,
    triu_to_matrix,
)


def small_sequence(stored: int = 3, total: int = 5, n: int = 4) -> GaussianSequence:
    rng = np.random.default_rng(0)
    a = rng.normal(size=(stored, n, 3, 3))
    return GaussianSequence(
        colors=rng.uniform(size=(n, 3)),
        opacities=rng.uniform(size=n),
        means=rng.normal(size=(stored, n, 3)),
        covs=matrix_to_triu(a @ a.transpose(0, 1, 3, 2)),
        n_frames=total,
        fps=25.0,
        camera_c2w=np.eye(4),
        camera_fov_y=0.6,
        ground=None,
    )


def test_triu_round_trip_and_order():
    m = np.array([[1.0, 2.0, 3.0], [2.0, 4.0, 5.0], [3.0, 5.0, 6.0]])
    assert matrix_to_triu(m).tolist() == [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]
    np.testing.assert_array_equal(triu_to_matrix(matrix_to_triu(m)), m)


def test_save_load_round_trip_and_frames_after_rest_repeat(tmp_path):
    seq = small_sequence(stored=3, total=5)
    path = seq.save(tmp_path / SEQUENCE_FILE)
    assert sorted(p.name for p in tmp_path.iterdir()) == [SEQUENCE_FILE]  # no temporary file left
    back = GaussianSequence.load(path)
    assert (len(back), back.stored_frames, back.fps, back.ground) == (5, 3, 25.0, None)
    np.testing.assert_array_equal(back.means, seq.means.astype(np.float32))
    np.testing.assert_array_equal(back.covs, seq.covs.astype(np.float32))
    means, covs = back.frame(4)  # after the stored frames: the last stored one holds
    np.testing.assert_array_equal(means, back.means[2])
    np.testing.assert_array_equal(covs, triu_to_matrix(back.covs[2]))
    with pytest.raises(IndexError, match="outside the clip's 5 frames"):
        back.frame(5)


def test_bad_files_say_what_is_wrong(tmp_path):
    seq = small_sequence()
    path = seq.save(tmp_path / "a.npz")
    with np.load(path) as data:
        arrays = dict(data)
    np.savez(tmp_path / "newer.npz", **{**arrays, "format": np.int64(FORMAT_VERSION + 1)})
    with pytest.raises(ValueError, match="format 2; this physgm reads format 1"):
        GaussianSequence.load(tmp_path / "newer.npz")
    np.savez(tmp_path / "partial.npz", **{k: v for k, v in arrays.items() if k != "covs"})
    with pytest.raises(ValueError, match=r"lacks the array\(s\) \['covs'\]"):
        GaussianSequence.load(tmp_path / "partial.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="not a readable Gaussian sequence"):
        GaussianSequence.load(tmp_path / "junk.npz")
    with pytest.raises(ValueError, match=r"covs must have shape \(3, 4, 6\)"):
        GaussianSequence(**{**vars(seq), "covs": seq.covs[:, :, :5]})
    with pytest.raises(ValueError, match="stores 3 frames of a 2-frame clip"):
        GaussianSequence(**{**vars(seq), "n_frames": 2})


def test_find_sequence_names_what_is_there(tmp_path):
    from physgm.view.server import find_sequence

    assert sequence_file("mean") == SEQUENCE_FILE and sequence_file("sample1") == "gaussians_t_sample1.npz"
    small_sequence().save(tmp_path / "gaussians_t_sample0.npz")
    assert find_sequence(tmp_path, "sample0") == tmp_path / "gaussians_t_sample0.npz"
    with pytest.raises(
        FileNotFoundError, match=r"has no gaussians_t.npz; it has \['gaussians_t_sample0.npz'\]"
    ):
        find_sequence(tmp_path)
    (tmp_path / "gaussians_t_sample0.npz").unlink()
    with pytest.raises(FileNotFoundError, match="re-run simulate.py"):
        find_sequence(tmp_path)


def test_cli_without_viser_says_how_to_install(tmp_path, monkeypatch, capsys):
    from physgm.view.__main__ import main

    small_sequence().save(tmp_path / SEQUENCE_FILE)
    monkeypatch.setitem(sys.modules, "viser", None)  # import viser now raises ImportError
    assert main([str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "pip install 'physgm[view]'" in err, err
    assert main([str(tmp_path / "absent")]) == 2
    assert "does not exist; give a run folder written by simulate.py" in capsys.readouterr().err


def test_simulate_writes_the_frames_it_renders(tmp_path):
    """A .ply run (no checkpoint): gaussians_t.npz holds the clip's frames, the frame PLYs' Gaussians."""
    from physgm.gaussians import Gaussians, read_ply, write_ply
    from physgm.pipeline import run_pipeline
    from physgm.pipeline.config import OutputSettings, RunConfig

    gen = torch.Generator().manual_seed(1)
    n = 400
    x = torch.randn(n, 3, generator=gen)
    x = x / x.norm(dim=1, keepdim=True) * torch.rand(n, 1, generator=gen) ** (1 / 3) * 0.3
    g = Gaussians(x, torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), torch.full((n, 3), 0.03),
                  torch.full((n,), 0.9), torch.rand(n, 3, generator=gen))  # fmt: skip
    write_ply(g, tmp_path / "blob.ply")
    out = OutputSettings(resolution=32, frames=6, fps=20.0, keyframes=3, progress=False, frame_plys=True)
    cfg = RunConfig(input=tmp_path / "blob.ply", output_dir=tmp_path / "run", ckpt=tmp_path / "absent.ckpt",
                    output=out)  # fmt: skip
    cfg.physics.material = "rubber"
    cfg.validate()
    report = run_pipeline(cfg).report
    seq = GaussianSequence.load(tmp_path / "run" / SEQUENCE_FILE)
    assert (len(seq), seq.fps, len(seq.colors)) == (6, 20.0, n)
    assert seq.ground == pytest.approx(0.0)  # the drop scene's ground
    eye = np.asarray(report["camera"]["eye_m"])
    np.testing.assert_allclose(seq.camera_c2w[:3, 3], eye, atol=1e-6)
    assert seq.camera_fov_y == pytest.approx(
        math.radians(report["camera"]["fov_deg"]), rel=1e-4
    )  # square image
    for t in range(6):
        ply = read_ply(tmp_path / "run" / "frames" / f"frame_{t:04d}.ply")
        means, covs = seq.frame(t)
        np.testing.assert_allclose(means, ply.means.numpy(), atol=1e-6)
        np.testing.assert_allclose(covs, ply.covariances().double().numpy(), rtol=1e-4, atol=1e-10)
    np.testing.assert_allclose(
        seq.colors, read_ply(tmp_path / "run" / "gaussians.ply").colors.numpy(), atol=1e-6
    )
    # It fell: the drop scene lowers the object between the first and the last frame.
    assert seq.frame(5)[0][:, 2].mean() < seq.frame(0)[0][:, 2].mean() - 0.005
    assert Path(tmp_path / "run" / "video.mp4").is_file()
