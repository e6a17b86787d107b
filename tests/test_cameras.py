import math

import pytest
import torch

from physgm.cameras import (
    Cameras,
    intrinsics_from_fov,
    opengl_to_opencv,
    orbit_cameras,
    pixel_rays,
    plucker_rays,
)


def project(cams: Cameras, points: torch.Tensor) -> torch.Tensor:
    """Pixel coordinates [C, P, 2] of world points [P, 3]."""
    cam = points @ cams.viewmats[:, :3, :3].transpose(1, 2) + cams.viewmats[:, None, :3, 3]
    uv = cam @ cams.Ks.transpose(1, 2)
    return uv[..., :2] / uv[..., 2:]


def test_orbit_camera_looks_at_target_with_z_up():
    cams = orbit_cameras(
        [0, 90, -45], [0, 30, 10], radius=2.0, fov_deg=40, width=64, height=48, target=(0.1, 0.2, 0.3)
    )
    uv = project(cams, torch.tensor([[0.1, 0.2, 0.3]]))
    torch.testing.assert_close(uv[:, 0], torch.tensor([[32.0, 24.0]]).expand(3, 2), atol=1e-4, rtol=0)
    # A point above the target appears higher in the image (smaller v).
    above = project(cams, torch.tensor([[0.1, 0.2, 0.5]]))
    assert (above[:, 0, 1] < 24).all()
    # Azimuth 0, elevation 0: the camera sits on +x at the given distance.
    torch.testing.assert_close(cams.centers[0], torch.tensor([2.1, 0.2, 0.3]))
    R = cams.c2w[:, :3, :3]
    torch.testing.assert_close(R.transpose(1, 2) @ R, torch.eye(3).expand(3, 3, 3), atol=1e-6, rtol=0)
    assert torch.allclose(torch.linalg.det(R), torch.ones(3))


def test_intrinsics_fov():
    K = intrinsics_from_fov(90.0, 100, 50)
    assert K[0, 0].item() == pytest.approx(50.0) and K[1, 1].item() == pytest.approx(50.0)
    assert K[0, 2].item() == 50 and K[1, 2].item() == 25
    with pytest.raises(ValueError, match="fov_deg"):
        intrinsics_from_fov(180, 10, 10)


def test_opengl_conversion_matches_opencv_look_at():
    cv = orbit_cameras([30], [20], 1.5, 40, 32, 32).c2w
    gl = cv.clone()
    gl[:, :3, 1:3] *= -1  # the OpenGL camera of the same view: y up, looking down -z
    torch.testing.assert_close(opengl_to_opencv(gl), cv)


def test_plucker_rays_shape_and_invariants():
    cams = orbit_cameras([0, 120], [0, 45], 1.8, 50, 12, 8)
    pl = plucker_rays(cams)
    assert pl.shape == (2, 6, 8, 12)
    d, m = pl[:, :3], pl[:, 3:]
    torch.testing.assert_close(d.norm(dim=1), torch.ones(2, 8, 12), atol=1e-6, rtol=0)
    torch.testing.assert_close(
        (d * m).sum(1), torch.zeros(2, 8, 12), atol=1e-5, rtol=0
    )  # moment is perpendicular
    # The moment does not depend on which point of the ray is used as origin.
    origins, dirs = pixel_rays(cams)
    shifted = torch.linalg.cross(origins + 0.7 * dirs, dirs, dim=-1).permute(0, 3, 1, 2)
    torch.testing.assert_close(shifted, m, atol=1e-5, rtol=0)
    # The centre ray of a look-at camera points at the target.
    centre = torch.nn.functional.normalize(-cams.centers, dim=-1)
    c = pixel_rays(orbit_cameras([0, 120], [0, 45], 1.8, 50, 13, 9))[1][:, 4, 6]
    torch.testing.assert_close(c, centre, atol=1e-5, rtol=0)


def test_camera_validation_and_resize():
    cams = orbit_cameras([0], [0], 1.0, 60, 64, 64)
    half = cams.resized(32, 32)
    assert half.Ks[0, 0, 0].item() == pytest.approx(cams.Ks[0, 0, 0].item() / 2)
    with pytest.raises(ValueError, match=r"c2w must have shape \[C, 4, 4\]"):
        Cameras(torch.eye(4), cams.Ks, 8, 8)
    bad = cams.c2w.clone()
    bad[0, 0, 3] = math.nan
    with pytest.raises(ValueError, match="non-finite"):
        Cameras(bad, cams.Ks, 8, 8)
    assert len(cams[0]) == 1
