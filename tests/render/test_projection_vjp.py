"""The hand-written projection VJP against Warp's generated adjoint of the projection kernel."""

from __future__ import annotations

import pytest
import torch
import warp as wp

from physgm.render import warp_kernels as K


def _arrays(scene: dict):
    f = {k: scene[k].to(torch.float32).contiguous() for k in ("means", "quats", "scales", "opacities")}
    cams = scene["viewmats"].to(torch.float32).contiguous(), scene["Ks"].to(torch.float32).contiguous()
    inputs = [
        wp.from_torch(f["means"], dtype=wp.vec3),
        wp.from_torch(f["quats"], dtype=wp.vec4),
        wp.from_torch(f["scales"], dtype=wp.vec3),
        wp.from_torch(f["opacities"]),
        wp.from_torch(cams[0], dtype=wp.mat44),
        wp.from_torch(cams[1], dtype=wp.mat33),
    ]
    return f, inputs


@pytest.mark.parametrize("focal", [40.0, 200.0])  # 200: most of the ball is off-screen (clamped rays)
def test_vjp_matches_warps_generated_adjoint(kit, focal):
    wp.init()
    width, height, num_c, num_n = 48, 40, 3, 400
    g = kit.random_gaussians(num_n, seed=3, radius=0.8)
    g["opacities"][:20] = 1e-3  # below the 1/255 alpha floor: culled, no gradient
    viewmats, Ks = kit.orbit_cameras(num_c, width, height, distance=1.6, focal=focal)
    scene = {**g, "viewmats": viewmats, "Ks": Ks}
    pairs = num_c * num_n
    gen = torch.Generator().manual_seed(1)
    v_means2d = torch.randn(pairs, 2, generator=gen)
    v_conics = torch.randn(pairs, 3, generator=gen) * 50.0
    f, inputs = _arrays(scene)
    scalars = [num_n, num_c, width, height, 0.01, 1e10, 0.3]

    outs = [wp.zeros(pairs, dtype=t) for t in (wp.vec2, wp.vec3, float, wp.vec2)]
    wp.launch(K.project_kernel, pairs, inputs + scalars + outs, device="cpu")
    depths = outs[2].numpy()
    assert (depths == 0).sum() >= 3 * 20  # the culled pairs are there

    # reference: Warp's generated adjoint
    ref = [wp.zeros(num_n, dtype=t) for t in (wp.vec3, wp.vec4, wp.vec3, float)]
    ref += [wp.zeros(num_c, dtype=wp.mat44), wp.zeros(num_c, dtype=wp.mat33)]
    adj_outs = [wp.from_torch(v_means2d, dtype=wp.vec2), wp.from_torch(v_conics, dtype=wp.vec3)]
    adj_outs += [wp.zeros(pairs, dtype=float), wp.zeros(pairs, dtype=wp.vec2)]
    fresh = [wp.zeros(pairs, dtype=t) for t in (wp.vec2, wp.vec3, float, wp.vec2)]
    wp.launch(
        K.project_kernel,
        pairs,
        inputs + scalars,
        outputs=fresh,
        adj_inputs=ref + [None] * 7,
        adj_outputs=adj_outs,
        adjoint=True,
        device="cpu",
    )

    got = [wp.zeros(num_n, dtype=t) for t in (wp.vec3, wp.vec4, wp.vec3)]
    wp.launch(K.project_vjp_kernel, pairs, [0] + inputs + scalars + adj_outs[:2] + got, device="cpu")
    for name, a, b in zip(("means", "quats", "scales"), got, ref[:3], strict=False):
        a, b = torch.from_numpy(a.numpy()), torch.from_numpy(b.numpy())
        assert b.abs().max() > 0, name
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-4 * b.abs().max().item(), msg=name)
    assert torch.from_numpy(got[0].numpy())[:20].abs().max() == 0  # culled Gaussians get nothing
