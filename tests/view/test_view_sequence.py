"""gaussians_t.npz: what simulate.py writes for the viewer, and how the viewer finds and reads it."""

from __future__ import annotations

import dataclasses
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from physgm.view.sequence import (
    FORMAT_VERSION,
    SEQUENCE_FILE,
    FollowedParticles,
    GaussianSequence,
    RigidPoses,
    StoredFrames,
    matrix_to_triu,
    sequence_file,
    triu_to_matrix,
)


def _spd(rng, shape) -> np.ndarray:  # [..., 6] upper triangles of random covariances
    a = rng.normal(size=(*shape, 3, 3))
    return matrix_to_triu(a @ np.swapaxes(a, -1, -2))


def _sequence(motion, total: int = 5) -> GaussianSequence:
    rng = np.random.default_rng(1)
    n = motion.n_gaussians
    return GaussianSequence(colors=rng.uniform(size=(n, 3)), opacities=rng.uniform(size=n), motion=motion,
                            n_frames=total, fps=25.0, camera_c2w=np.eye(4), camera_fov_y=0.6)  # fmt: skip


def small_sequence(stored: int = 3, total: int = 5, n: int = 4) -> GaussianSequence:
    rng = np.random.default_rng(0)
    return _sequence(StoredFrames(rng.normal(size=(stored, n, 3)), _spd(rng, (stored, n))), total)


def followed(stored: int = 3, n: int = 7, p: int = 5, k: int = 3) -> FollowedParticles:
    rng = np.random.default_rng(2)
    w = rng.uniform(0.1, 1.0, (n, k))
    return FollowedParticles(
        rest_covs=_spd(rng, (n,)) * 1e-4,
        index=rng.integers(0, p, (n, k)).astype(np.int32),
        weight=(w / w.sum(1, keepdims=True)).astype(np.float32),
        offset=rng.normal(scale=0.01, size=(n, k, 3)).astype(np.float32),
        x=rng.normal(size=(stored, p, 3)).astype(np.float32),
        F=(np.eye(3) + 0.2 * rng.normal(size=(stored, p, 3, 3))).astype(np.float32),
    )


def rigid(stored: int = 3, n: int = 6) -> RigidPoses:
    rng = np.random.default_rng(3)
    q, _ = np.linalg.qr(rng.normal(size=(stored, 3, 3)))
    rot = q * np.sign(np.linalg.det(q))[:, None, None]  # proper rotations
    return RigidPoses(
        rest_means=rng.normal(size=(n, 3)).astype(np.float32),
        rest_covs=_spd(rng, (n,)).astype(np.float32) * 1e-4,
        rotations=rot,
        coms=rng.normal(size=(stored, 3)),
        rest_com=rng.normal(size=3),
    )


def test_triu_round_trip_and_order():
    m = np.array([[1.0, 2.0, 3.0], [2.0, 4.0, 5.0], [3.0, 5.0, 6.0]])
    assert matrix_to_triu(m).tolist() == [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]
    np.testing.assert_array_equal(triu_to_matrix(matrix_to_triu(m)), m)


@pytest.mark.parametrize("make", [small_sequence, lambda: _sequence(followed()), lambda: _sequence(rigid())])
def test_save_load_round_trip_and_frames_after_rest_repeat(tmp_path, make):
    seq = make()
    path = seq.save(tmp_path / SEQUENCE_FILE)
    assert sorted(p.name for p in tmp_path.iterdir()) == [SEQUENCE_FILE]  # no temporary file left
    back = GaussianSequence.load(path)
    assert (len(back), back.stored_frames, back.fps, back.ground) == (5, 3, 25.0, None)
    assert type(back.motion) is type(seq.motion)
    for t in range(3):
        for got, want in zip(back.frame(t), seq.frame(t), strict=True):
            np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-7)
    for got, want in zip(back.frame(4), back.frame(2), strict=True):  # the last stored frame holds
        np.testing.assert_array_equal(got, want)
    with pytest.raises(IndexError, match="outside the clip's 5 frames"):
        back.frame(5)


def test_followed_particles_move_gaussians_as_the_coupling_does():
    """A frame of ``FollowedParticles`` is ``Followers.apply`` with F Sigma_0 F^T, the torch twin of
    what simulate.py renders."""
    from physgm.sim.coupling import deform_covariances
    from physgm.sim.sampling import Followers

    motion = followed()
    f = Followers(torch.from_numpy(motion.index).long(), torch.from_numpy(motion.weight),
                  torch.from_numpy(motion.offset))  # fmt: skip
    for s in range(motion.stored_frames):
        means, Fg = f.apply(torch.from_numpy(motion.x[s]).double(), torch.from_numpy(motion.F[s]).double())
        covs = deform_covariances(torch.from_numpy(triu_to_matrix(motion.rest_covs)).double(), Fg.double())
        got_means, got_covs = motion.frame(s)
        np.testing.assert_allclose(got_means, means.numpy(), rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(got_covs, covs.numpy(), rtol=1e-4, atol=1e-9)


def test_a_followed_clips_extent_comes_from_its_particles_and_bounds_its_frames():
    # GaussianSequence.extent reads a followed clip from its particles alone (a 1.2M-Gaussian clip's
    # frames took 10-13 s): the mean centre exactly, lo / hi / the variance as bounds.
    seq = _sequence(followed(stored=4, n=60, p=9, k=4))
    extent = seq.extent()
    frames = [seq.motion.frame(s) for s in range(4)]
    means = np.concatenate([m for m, _ in frames])
    np.testing.assert_allclose(extent.centre, means.mean(0, dtype=np.float64), rtol=1e-5, atol=1e-6)
    assert (extent.lo <= means.min(0)).all() and (extent.hi >= means.max(0)).all()
    assert (extent.hi - extent.lo < 1.5 * np.ptp(means, axis=0) + 0.2).all()  # a bound, not the world
    exact = max(float(c[:, np.arange(3), np.arange(3)].max()) for _, c in frames)
    assert exact <= extent.max_variance <= 30 * exact


def test_rigid_poses_turn_about_the_centre_of_mass():
    motion = rigid()
    means, covs = motion.frame(1)
    rot = motion.rotations[1]
    want = (motion.rest_means - motion.rest_com) @ rot.T + motion.coms[1]
    np.testing.assert_allclose(means, want, atol=1e-6)
    np.testing.assert_allclose(covs, rot @ triu_to_matrix(motion.rest_covs) @ rot.T, rtol=1e-5, atol=1e-12)


def test_the_file_grows_with_the_particles_not_with_the_gaussians_times_frames(tmp_path):
    """50 frames of 20,000 Gaussians following 300 particles: each frame stores the particles
    (14 kB), not every Gaussian's centre and covariance (720 kB)."""
    motion = followed(stored=50, n=20_000, p=300, k=8)
    size = _sequence(motion, 50).save(tmp_path / "a.npz").stat().st_size
    per_gaussian = 4 * (3 + 1 + 6 + 8 * (1 + 1 + 3))  # colour, opacity, rest covariance, followers
    per_frame = 4 * 300 * (3 + 9)
    assert size < 20_000 * per_gaussian + 50 * per_frame + 10_000
    assert size < 0.3 * 50 * 20_000 * 4 * (3 + 6)  # the centres and covariances of every frame


def test_a_file_of_format_1_still_loads(tmp_path):
    seq = small_sequence()
    arrays = {k: v for k, v in np.load(seq.save(tmp_path / "new.npz")).items() if k != "motion"}
    np.savez(tmp_path / "old.npz", **{**arrays, "format": np.int64(1)})
    back = GaussianSequence.load(tmp_path / "old.npz")
    np.testing.assert_array_equal(back.motion.means, seq.motion.means.astype(np.float32))
    np.testing.assert_array_equal(back.motion.covs, seq.motion.covs.astype(np.float32))


def test_bad_files_say_what_is_wrong(tmp_path):
    seq = _sequence(followed())
    path = seq.save(tmp_path / "a.npz")
    with np.load(path) as data:
        arrays = dict(data)
    np.savez(tmp_path / "newer.npz", **{**arrays, "format": np.int64(FORMAT_VERSION + 1)})
    with pytest.raises(ValueError, match="format 3; this physgm reads formats 1 and 2"):
        GaussianSequence.load(tmp_path / "newer.npz")
    np.savez(tmp_path / "partial.npz", **{k: v for k, v in arrays.items() if k != "particle_F"})
    with pytest.raises(ValueError, match=r"lacks the array\(s\) \['particle_F'\]"):
        GaussianSequence.load(tmp_path / "partial.npz")
    np.savez(tmp_path / "kind.npz", **{**arrays, "motion": np.str_("wobble")})
    with pytest.raises(ValueError, match="unknown motion 'wobble'; a sequence file holds one of"):
        GaussianSequence.load(tmp_path / "kind.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="not a readable Gaussian sequence"):
        GaussianSequence.load(tmp_path / "junk.npz")
    frames = small_sequence()
    with pytest.raises(ValueError, match=r"covs must have shape \(3, 4, 6\)"):
        StoredFrames(frames.motion.means, frames.motion.covs[:, :, :5])
    with pytest.raises(ValueError, match="stores 3 frames of a 2-frame clip"):
        GaussianSequence(**{**vars(frames), "n_frames": 2})
    with pytest.raises(ValueError, match=r"colors must have shape \(7, 3\)"):
        GaussianSequence(**{**vars(seq), "colors": seq.colors[:3]})
    motion = followed()
    with pytest.raises(ValueError, match="index must name particles 0 to 4"):
        dataclasses.replace(motion, index=motion.index + 5)


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


@pytest.mark.parametrize(
    ("n", "frames", "material", "E", "mode", "motion"),
    [
        (400, 6, "jelly", 2e3, "mpm", StoredFrames),  # more particles than Gaussians: frames are smaller
        (60_000, 16, "jelly", 2e3, "mpm", FollowedParticles),
        (400, 6, "metal", None, "rigid", RigidPoses),
    ],
)
def test_simulate_writes_the_frames_it_renders(tmp_path, n, frames, material, E, mode, motion):
    """A .ply run (no checkpoint): gaussians_t.npz holds the clip's frames, the frame PLYs' Gaussians,
    in the smaller of its two forms for a simulated body."""
    from physgm.gaussians import Gaussians, read_ply, write_ply
    from physgm.pipeline import run_pipeline
    from physgm.pipeline.config import OutputSettings, RunConfig

    gen = torch.Generator().manual_seed(1)
    x = torch.randn(n, 3, generator=gen)
    x = x / x.norm(dim=1, keepdim=True) * torch.rand(n, 1, generator=gen) ** (1 / 3) * 0.3
    g = Gaussians(x, torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), torch.full((n, 3), 0.03),
                  torch.full((n,), 0.9), torch.rand(n, 3, generator=gen))  # fmt: skip
    write_ply(g, tmp_path / "blob.ply")
    out = OutputSettings(resolution=32, frames=frames, fps=20.0, keyframes=3, progress=False, frame_plys=True)
    cfg = RunConfig(input=tmp_path / "blob.ply", output_dir=tmp_path / "run", ckpt=tmp_path / "absent.ckpt",
                    output=out)  # fmt: skip
    cfg.physics.material, cfg.physics.E = material, E
    cfg.validate()
    report = run_pipeline(cfg).report
    assert report["mode"] == mode
    seq = GaussianSequence.load(tmp_path / "run" / SEQUENCE_FILE)
    assert isinstance(seq.motion, motion), (report["particles"], seq.stored_frames)
    assert (len(seq), seq.fps, len(seq.colors)) == (frames, 20.0, n)
    assert seq.ground == pytest.approx(0.0)  # the drop scene's ground
    eye = np.asarray(report["camera"]["eye_m"])
    np.testing.assert_allclose(seq.camera_c2w[:3, 3], eye, atol=1e-6)
    assert seq.camera_fov_y == pytest.approx(
        math.radians(report["camera"]["fov_deg"]), rel=1e-4
    )  # square image
    for t in range(frames):
        ply = read_ply(tmp_path / "run" / "frames" / f"frame_{t:04d}.ply")
        means, covs = seq.frame(t)
        np.testing.assert_allclose(means, ply.means.numpy(), atol=1e-6)
        np.testing.assert_allclose(covs, ply.covariances().double().numpy(), rtol=1e-4, atol=1e-9)
    np.testing.assert_allclose(
        seq.colors, read_ply(tmp_path / "run" / "gaussians.ply").colors.numpy(), atol=1e-6
    )
    # It fell: the drop scene lowers the object between the first and the last frame.
    assert seq.frame(frames - 1)[0][:, 2].mean() < seq.frame(0)[0][:, 2].mean() - 0.005
    assert Path(tmp_path / "run" / "video.mp4").is_file()
