"""Gaussian coupling: move rest Gaussians with a simulated deformation.

A Gaussian with rest covariance Sigma_0 = R_0 S_0^2 R_0^T carried by a local deformation gradient F
has covariance Sigma_t = F Sigma_0 F^T (PhysGaussian, eq. 6). Renderers take (quat, scale), so the
deformed covariance is split back into a rotation and linear scales by a symmetric eigen
decomposition. The eigenvectors come out in arbitrary order and sign; we match them to the
deformed rest axes F R_0 so a Gaussian keeps its axis labelling from frame to frame (the rendered
image does not depend on that choice, but a stable labelling keeps quats continuous in time).

The torch functions are batched over N and differentiable where eigh is; ``follow_and_deform``
fuses follower interpolation and the split into one Warp kernel (CPU or CUDA) for per-frame use.
Both work for Gaussians from the model or a 3DGS PLY.
"""

from __future__ import annotations

import itertools

import torch
import warp as wp
from torch import Tensor

from physgm.gaussians import Gaussians, quat_to_rotmat, rotmat_to_quat
from physgm.parallel import run_launches
from physgm.sim.linalg import sym_eig3
from physgm.sim.sampling import Followers

# The 6 permutations of three axes, [6, 3]: row k maps rest axis i to eigenvector PERMS[k, i].
_PERMS = torch.tensor(list(itertools.permutations(range(3))))


def deform_covariances(
    covs: Tensor,  # [N, 3, 3] rest covariances, m^2
    F: Tensor,  # [N, 3, 3] deformation gradients
) -> Tensor:
    """Sigma_t = F Sigma_0 F^T, [N, 3, 3] in m^2."""
    return F @ covs @ F.transpose(-1, -2)


def covariance_to_quat_scale(
    covs: Tensor,  # [N, 3, 3] symmetric positive semi-definite, m^2
    ref_axes: Tensor | None = None,  # [N, 3, 3] columns: preferred axis directions (unnormalised ok)
) -> tuple[Tensor, Tensor]:
    """Split covariances into unit quaternions (w, x, y, z) and linear scales.

    Args:
        covs: [N, 3, 3] covariances.
        ref_axes: [N, 3, 3] whose column i is the direction axis i should keep (e.g. F R_0 S_0);
            without it the axes come sorted by increasing scale.

    Returns:
        quats [N, 4] (w >= 0) and scales [N, 3] in m, with R diag(s^2) R^T = covs.
    """
    dtype = covs.dtype
    # float64 eigh: scales span ~1e-4..1e-1 m, so covariances span 1e-8..1e-2 m^2.
    c64 = covs.double()
    c64 = 0.5 * (c64 + c64.transpose(-1, -2))
    evals, evecs = torch.linalg.eigh(c64)  # [N, 3], [N, 3, 3] columns
    evals = evals.clamp_min(0.0)
    if ref_axes is not None:
        # score[n, j, i] = |u_j . a_i|: how well eigenvector j matches rest axis i.
        proj = evecs.transpose(-1, -2) @ ref_axes.double()  # [N, 3, 3]
        perms = _PERMS.to(covs.device)
        cols = torch.arange(3, device=covs.device)
        scores = proj.abs()[:, perms, cols].sum(-1)  # [N, 6]
        best = perms[scores.argmax(-1)]  # [N, 3]: eigenvector index for each rest axis
        evecs = torch.gather(evecs, 2, best[:, None, :].expand(-1, 3, -1))
        evals = torch.gather(evals, 1, best)
        dots = torch.gather(proj, 1, best[:, None, :]).squeeze(1)  # [N, 3]: u_best[i] . a_i
        signs = torch.where(dots < 0, -1.0, 1.0).to(evecs)
        evecs = evecs * signs[:, None, :]
        # A reflection is not a rotation: flip the axis that matches its reference worst.
        flip = torch.linalg.det(evecs) < 0
        if flip.any():
            worst = dots.abs().argmin(-1)
            fix = torch.ones_like(signs)
            fix[flip, worst[flip]] = -1.0
            evecs = evecs * fix[:, None, :]
    else:
        flip = torch.linalg.det(evecs) < 0
        evecs = torch.where(
            flip[:, None, None],
            evecs * torch.tensor([1.0, 1.0, -1.0], dtype=evecs.dtype, device=evecs.device),
            evecs,
        )
    quats = rotmat_to_quat(evecs).to(dtype)
    return quats, evals.sqrt().to(dtype)


def deform_gaussians(
    gaussians: Gaussians,
    means: Tensor,  # [N, 3] deformed centres, m
    F: Tensor,  # [N, 3, 3] deformation gradient at each Gaussian
) -> Gaussians:
    """Gaussians moved to ``means`` with covariances F Sigma_0 F^T (colours, opacities kept)."""
    n = len(gaussians)
    if means.shape != (n, 3) or F.shape != (n, 3, 3):
        raise ValueError(
            f"deform_gaussians needs means [N, 3] and F [N, 3, 3] with N = {n}, got {tuple(means.shape)} "
            f"and {tuple(F.shape)}"
        )
    rot0 = quat_to_rotmat(gaussians.quats)
    axes0 = rot0 * gaussians.scales[:, None, :]  # [N, 3, 3]: columns R_0 S_0, so Sigma_0 = A A^T
    axes_t = F.to(axes0) @ axes0
    covs_t = axes_t @ axes_t.transpose(-1, -2)
    quats, scales = covariance_to_quat_scale(covs_t, ref_axes=axes_t)
    return Gaussians(
        means=means.to(gaussians.means),
        quats=quats,
        scales=scales,
        opacities=gaussians.opacities,
        colors=gaussians.colors,
        sh_rest=gaussians.sh_rest,
    )


def quat_multiply(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product a * b of quaternions (w, x, y, z), [..., 4]."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        dim=-1,
    )


def rigid_transform_gaussians(
    gaussians: Gaussians,
    rotation: Tensor,  # [3, 3] world rotation
    translation: Tensor,  # [3] m
    center: Tensor,  # [3] m, rest point the rotation turns about (the centre of mass)
) -> Gaussians:
    """Gaussians after x -> R (x - center) + center + translation; scales unchanged.

    The rigid path needs no decomposition: the rotation composes with each quaternion.
    """
    rot = rotation.to(gaussians.means)
    means = (gaussians.means - center.to(rot)) @ rot.T + center.to(rot) + translation.to(rot)
    q_rot = rotmat_to_quat(rot[None])  # [1, 4]
    quats = quat_multiply(q_rot.expand_as(gaussians.quats), gaussians.quats)
    quats = quats * torch.where(quats[:, :1] < 0, -1.0, 1.0)
    return Gaussians(
        means=means,
        quats=quats,
        scales=gaussians.scales,
        opacities=gaussians.opacities,
        colors=gaussians.colors,
        sh_rest=gaussians.sh_rest,
    )


# ----------------------------------------------------------------------------------------------
# Fast path: followers + deformation + (quat, scale) split fused in one Warp kernel per frame.
# ``deform_gaussians`` / ``Followers.apply`` above are its torch twin (compared in the tests).


@wp.func
def _perm_axis(p: int, k: int) -> int:
    """Eigenvector index that rest axis k takes under permutation p (the 6 of ``_PERMS``)."""
    if p == 0:
        return k
    if p == 1:
        return wp.where(k == 0, 0, wp.where(k == 1, 2, 1))
    if p == 2:
        return wp.where(k == 0, 1, wp.where(k == 1, 0, 2))
    if p == 3:
        return wp.where(k == 0, 1, wp.where(k == 1, 2, 0))
    if p == 4:
        return wp.where(k == 0, 2, wp.where(k == 1, 0, 1))
    return wp.where(k == 0, 2, wp.where(k == 1, 1, 0))


@wp.func
def _followed(
    i: int,
    index: wp.array2d(dtype=int),
    weight: wp.array2d(dtype=float),
    offset: wp.array2d(dtype=wp.vec3),
    px: wp.array(dtype=wp.vec3),
    pF: wp.array(dtype=wp.mat33),
):
    """Gaussian i's centre sum_k w_k (x_j + F_j o_k) and deformation gradient sum_k w_k F_j."""
    x = wp.vec3(0.0)
    F = wp.mat33(0.0)
    for k in range(index.shape[1]):
        j = index[i, k]
        w = weight[i, k]
        x += w * (px[j] + pF[j] * offset[i, k])
        F += w * pF[j]
    return x, F


def _followed_arrays(followers: Followers, x: Tensor, F: Tensor, device: torch.device) -> list[wp.array]:
    """``_followed``'s inputs as Warp views: index, weight, offset, particle positions and F."""
    return [
        wp.from_torch(followers.index.int().contiguous(), dtype=wp.int32),
        wp.from_torch(followers.weight.float().contiguous(), dtype=wp.float32),
        wp.from_torch(followers.offset.float().contiguous(), dtype=wp.vec3),
        wp.from_torch(x.to(device).float().contiguous(), dtype=wp.vec3),
        wp.from_torch(F.to(device).float().contiguous(), dtype=wp.mat33),
    ]


@wp.kernel
def _follow_and_deform(
    start: int,  # first Gaussian of this launch (a launch covers a range; see _launch_ranges)
    index: wp.array2d(dtype=int),  # [N, K] particle indices
    weight: wp.array2d(dtype=float),  # [N, K]
    offset: wp.array2d(dtype=wp.vec3),  # [N, K] rest offsets X_g - X_j, m
    px: wp.array(dtype=wp.vec3),  # [P] particle positions, m
    pF: wp.array(dtype=wp.mat33),  # [P] particle deformation gradients
    quats0: wp.array(dtype=wp.vec4),  # [N] rest (w, x, y, z), normalised here
    scales0: wp.array(dtype=wp.vec3),  # [N] rest, m
    means: wp.array(dtype=wp.vec3),  # [N] out, m
    quats: wp.array(dtype=wp.vec4),  # [N] out (w, x, y, z), w >= 0
    scales: wp.array(dtype=wp.vec3),  # [N] out, m
):
    i = start + wp.tid()
    x, F = _followed(i, index, weight, offset, px, pF)
    means[i] = x
    q0 = quats0[i]
    rot0 = wp.quat_to_matrix(wp.normalize(wp.quat(q0[1], q0[2], q0[3], q0[0])))
    s0 = scales0[i]
    A = F * wp.matrix_from_cols(s0[0] * rot0[:, 0], s0[1] * rot0[:, 1], s0[2] * rot0[:, 2])  # F R_0 S_0
    # Split A / |A| and scale back: in m (scales ~1e-2) sym_eig3's cross products of a nearly
    # round Gaussian's covariance fall to float32's denormals (~1e-44), and its axes came out up
    # to 10 % off.
    size = wp.sqrt(wp.ddot(A, A))
    if size > 0.0:
        A = A / size
    Q, beta = sym_eig3(A * wp.transpose(A))
    proj = wp.transpose(Q) * A  # proj[j, k] = u_j . a_k
    best = int(0)  # noqa: UP018 (Warp: a dynamic variable, mutated in the loop)
    best_score = float(-1.0)  # noqa: UP018
    for p in range(6):
        score = float(0.0)  # noqa: UP018
        for k in range(3):
            score += wp.abs(proj[_perm_axis(p, k), k])
        if score > best_score:
            best_score = score
            best = p
    R = wp.mat33(0.0)
    s = wp.vec3(0.0)
    worst = int(0)  # noqa: UP018
    worst_dot = float(1.0e30)  # noqa: UP018
    for k in range(3):
        e = _perm_axis(best, k)
        d = proj[e, k]
        sign = wp.where(d < 0.0, -1.0, 1.0)
        for r in range(3):
            R[r, k] = sign * Q[r, e]
        s[k] = size * wp.sqrt(wp.max(beta[e], 0.0))
        if wp.abs(d) < worst_dot:
            worst_dot = wp.abs(d)
            worst = k
    if wp.determinant(R) < 0.0:  # a reflection: flip the axis that matches its reference worst
        for r in range(3):
            R[r, worst] = -R[r, worst]
    q = wp.quat_from_matrix(R)  # (x, y, z, w)
    if q[3] < 0.0:
        q = -q
    quats[i] = wp.vec4(q[3], q[0], q[1], q[2])
    scales[i] = s


def follow_and_deform(
    gaussians: Gaussians,
    followers: Followers,
    x: Tensor,  # [P, 3] particle positions, m
    F: Tensor,  # [P, 3, 3] particle deformation gradients
    num_threads: int = 2,  # CPU threads (one launch each over a range of the Gaussians)
) -> Gaussians:
    """Deformed Gaussians of one frame: ``deform_gaussians(g, *followers.apply(x, F))`` in one Warp kernel."""
    wp.init()
    device = wp.device_from_torch(gaussians.means.device)
    n = len(gaussians)
    arrays = [
        *_followed_arrays(followers, x, F, gaussians.means.device),
        wp.from_torch(gaussians.quats.detach().float().contiguous(), dtype=wp.vec4),
        wp.from_torch(gaussians.scales.detach().float().contiguous(), dtype=wp.vec3),
    ]
    means, quats, scales = (torch.empty(n, c, device=gaussians.means.device) for c in (3, 4, 3))
    outs = [
        wp.from_torch(means, dtype=wp.vec3),
        wp.from_torch(quats, dtype=wp.vec4),
        wp.from_torch(scales, dtype=wp.vec3),
    ]
    _launch_ranges(_follow_and_deform, n, arrays + outs, device, num_threads)
    return Gaussians(means, quats, scales, gaussians.opacities, gaussians.colors, gaussians.sh_rest)


@wp.kernel
def _follow_covariance(
    start: int,  # first Gaussian of this launch
    index: wp.array2d(dtype=int),  # [N, K] particle indices
    weight: wp.array2d(dtype=float),  # [N, K]
    offset: wp.array2d(dtype=wp.vec3),  # [N, K] rest offsets X_g - X_j, m
    px: wp.array(dtype=wp.vec3),  # [P] particle positions, m
    pF: wp.array(dtype=wp.mat33),  # [P] particle deformation gradients
    covs0: wp.array(dtype=wp.mat33),  # [N] rest covariances, m^2
    means: wp.array(dtype=wp.vec3),  # [N] out, m
    covs: wp.array(dtype=wp.mat33),  # [N] out, m^2
):
    i = start + wp.tid()
    x, F = _followed(i, index, weight, offset, px, pF)
    means[i] = x
    covs[i] = F * covs0[i] * wp.transpose(F)


def follow_covariances(
    followers: Followers,
    covs0: Tensor,  # [N, 3, 3] rest covariances, m^2
    x: Tensor,  # [P, 3] particle positions, m
    F: Tensor,  # [P, 3, 3] particle deformation gradients
    num_threads: int = 2,  # CPU threads (one launch each over a range of the Gaussians)
) -> tuple[Tensor, Tensor]:  # [N, 3] m, [N, 3, 3] m^2
    """Centres and covariances F Sigma_0 F^T of Gaussians that follow particles, without the
    (quat, scale) split: ``Followers.apply`` and ``deform_covariances`` in one Warp kernel, for
    reading a stored clip (``physgm.view.motion``)."""
    wp.init()
    device = wp.device_from_torch(covs0.device)
    n = covs0.shape[0]
    arrays = [
        *_followed_arrays(followers, x, F, covs0.device),
        wp.from_torch(covs0.float().contiguous(), dtype=wp.mat33),
    ]
    means, covs = torch.empty(n, 3, device=covs0.device), torch.empty(n, 3, 3, device=covs0.device)
    outs = [wp.from_torch(means, dtype=wp.vec3), wp.from_torch(covs, dtype=wp.mat33)]
    _launch_ranges(_follow_covariance, n, arrays + outs, device, num_threads)
    return means, covs


# Fewer Gaussians than this run on one thread: the hand-off to a helper costs more than it saves
# (follow_and_deform, K = 8, on this 2-core CPU: 1,000 Gaussians 0.40 ms on one thread and 0.46 on
# two; 2,000 0.68 and 0.50 ms; 32,000 10.5 and 5.6-6.5 ms).
PARALLEL_MIN_GAUSSIANS = 2048


def _launch_ranges(kernel, n: int, args: list, device, num_threads: int) -> None:
    """``kernel`` over Gaussians 0..n-1, on the CPU split into ``num_threads`` ranges run at once
    (a Warp CPU launch runs on one core and releases the GIL); each Gaussian is computed alone,
    so the result does not depend on the split."""
    parts = num_threads if device.is_cpu and n >= PARALLEL_MIN_GAUSSIANS else 1
    cuts = [n * k // parts for k in range(parts + 1)]
    run_launches(kernel, [(hi - lo, [lo, *args]) for lo, hi in itertools.pairwise(cuts) if hi > lo], device)
